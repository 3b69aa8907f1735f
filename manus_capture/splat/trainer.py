"""The object model: static Gaussians fitted to calibrated views with masks.

Inputs are plain tensors (`Views`): images (V,H,W,3) in [0,1], intrinsics K (V,3,3) in pixels,
world-to-camera rotations R (V,3,3) and translations t (V,3) as in CameraRig
(x_cam = R x + t), and optional object masks (V,H,W). Images are assumed undistorted.

With masks, the training target of a view is its image on the object and the background colour
elsewhere, so the model holds the object alone; Gaussians are initialized inside the visual hull
of the masks and, during densification, those projecting outside a mask are pruned.

Surfels (ObjectConfig.thin): where the model's Gaussians stand for the surface itself (contacts
are measured between Gaussian centres), they start as discs on the visual hull's boundary, facing
out, and stay thin along their normal. A round Gaussian covers the silhouette from inside the
surface; a disc seen edge-on only covers it from the surface.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch
from scipy.spatial import cKDTree

from manus_core.progress import Progress, silent

from .gaussians import Gaussians
from .losses import LPIPS, LossWeights, image_loss, psnr, ssim, training_lpips
from .optimize import Densification, LearningRates, Strategy, decay_means_lr, make_optimizers, optimize_step
from .rasterize import EPS2D, rasterize
from .strategy import DensifyStrategy, nearest_pixels, prune_outside_masks


def world_to_camera(R, t) -> torch.Tensor:
    """4x4 world-to-camera matrices (C,4,4) float32 from CameraRig-style R (C,3,3), t (C,3) of
    any array type (np.array copies: CameraRig's arrays are read-only, which torch warns about)."""
    R, t = (x.float() if torch.is_tensor(x) else torch.from_numpy(np.array(x, dtype=np.float32)) for x in (R, t))
    viewmats = torch.eye(4).repeat(len(R), 1, 1)
    viewmats[:, :3, :3] = R
    viewmats[:, :3, 3] = t
    return viewmats


NEAR_MASK_PX = 2


@dataclass
class Views:
    """Calibrated views: images (V,H,W,3) in [0,1], Ks (V,3,3), viewmats (V,4,4), masks (V,H,W) or
    None, optionally the camera ids (V,) they came from, and optionally `backgrounds` (V,H,W,3):
    what each camera sees behind the subject (the empty scene), for renders to be put over."""

    images: torch.Tensor
    Ks: torch.Tensor
    viewmats: torch.Tensor
    masks: torch.Tensor | None = None
    ids: tuple[str, ...] | None = None
    backgrounds: torch.Tensor | None = None

    @classmethod
    def from_rig(cls, images: torch.Tensor, K: torch.Tensor, R: torch.Tensor, t: torch.Tensor,
                 masks: torch.Tensor | None = None, ids=None) -> "Views":
        """Views from CameraRig-style K, R, t (any array type; float32 tensors are made)."""
        # np.array copies: CameraRig's arrays are read-only, which torch warns about
        K = K.float() if torch.is_tensor(K) else torch.from_numpy(np.array(K, dtype=np.float32))
        images = torch.as_tensor(images, dtype=torch.float32)
        masks = None if masks is None else torch.as_tensor(masks, dtype=torch.bool)
        return cls(images, K, world_to_camera(R, t), masks, None if ids is None else tuple(ids))

    def __len__(self) -> int:
        return self.images.shape[0]

    def to(self, device: str | torch.device) -> "Views":
        return Views(self.images.to(device), self.Ks.to(device), self.viewmats.to(device),
                     None if self.masks is None else self.masks.to(device), self.ids,
                     None if self.backgrounds is None else self.backgrounds.to(device))

    @property
    def width(self) -> int:
        return self.images.shape[2]

    @property
    def height(self) -> int:
        return self.images.shape[1]

    @property
    def centres(self) -> torch.Tensor:
        """Camera centres in the world, (V,3)."""
        R, t = self.viewmats[:, :3, :3], self.viewmats[:, :3, 3]
        return -torch.einsum("vji,vj->vi", R, t)

    def subset(self, index) -> "Views":
        index = torch.as_tensor(index, dtype=torch.long)
        return Views(self.images[index], self.Ks[index], self.viewmats[index],
                     None if self.masks is None else self.masks[index],
                     None if self.ids is None else tuple(self.ids[i] for i in index.tolist()),
                     None if self.backgrounds is None else self.backgrounds[index])

    def targets(self, background: torch.Tensor) -> torch.Tensor:
        """Images with everything outside the masks set to the background colour; with
        backgrounds, to those, beyond NEAR_MASK_PX of a mask."""
        if self.masks is None:
            return self.images
        if self.backgrounds is None:
            return torch.where(self.masks[..., None], self.images, background.to(self.images.dtype))
        # a pixel just outside a mask is still partly the subject (under half of it): its image
        # is its target, not the empty scene
        size = 2 * NEAR_MASK_PX + 1
        near = torch.nn.functional.max_pool2d(self.masks[:, None].float(), size, 1, NEAR_MASK_PX)[:, 0] > 0
        return torch.where(near[..., None], self.images, self.backgrounds)

    def composite(self, rendered: torch.Tensor, alpha: torch.Tensor, background: torch.Tensor,
                  index: slice = slice(None)) -> torch.Tensor:
        """Renders (V,H,W,3) of views `index`, made over the colour `background` with their alpha
        (V,H,W,1), put over those views' backgrounds where they have them. A pixel on a subject's
        silhouette is partly the subject and partly the scene behind it: over a plain colour, not
        even an exact model of the subject matches it."""
        if self.backgrounds is None:
            return rendered
        return rendered + (1 - alpha) * (self.backgrounds[index] - background)


# At the capture takes' resolutions a pixel is a few millimetres on the subject, and 3DGS's blur
# draws a surface of splats about a pixel larger than it is: the fit then pulls the centres that
# far inside. On the 12-camera 320x180 demo the hand's centres sat a median 2.9 mm inside its
# surface at 0.3 and 1.7 mm at 0.05 (the object's: 2.2 and 1.6 mm with its old masks).
SURFACE_EPS2D = 0.05
SURFEL_THIN_M = 3e-4
SURFEL_MAX_SCALE_M = 2e-3
# The silhouette term (rendered alpha against the mask): the colour loss alone hardly tells a
# surface's edge from a dark edge pixel, and surfels left to it drift inside the silhouette they
# cover. On a simulated hand take with true poses, masks and cameras, the surfels' centres ended a
# median 2.9 mm inside the hand's surface without it and 1.2 mm with it.
SURFEL_MASK_WEIGHT = 3.0
# The loss of the short CPU configurations (ObjectConfig.fast, HandConfig.fast and their surfels):
# the MANUS paper's without LPIPS. On make demo's session (24 cameras, 320x180, 400 steps each)
# LPIPS at 0.1 made training 22-27 % slower (51 -> 62-65 s) for held-out PSNR on the subjects'
# pixels of -0.18 dB (hand) and +0.04 dB (object) and LPIPS -0.0003 and 0 (docs/splat.md).
FAST_LOSS = LossWeights(lpips=0.0)
# Their step sizes: the colour's 4x 3DGS's, its view-dependent part (SH degree 1) as fast and from
# the first step, the scales' 2x. 3DGS steps the view-dependent coefficients at a twentieth of the
# base colour's rate and adds a degree every 1000 of its 30k steps: in a few hundred steps they
# hardly moved, and every surfel kept one colour for every view of a surface whose shading changes
# with the view. On make demo's session (400 steps) learning them took the object's held-out PSNR
# on its pixels from 24.40 to 26.68 dB and the hand's from 21.11 to 21.32 (docs/splat.md).
FAST_LR = LearningRates(sh0=1e-2, shN=1e-2, scales=1e-2)


@dataclass
class ObjectConfig:
    """Settings of `train_object`. densify: any strategy with gsplat's API (optimize.Strategy);
    None keeps the number of Gaussians fixed."""

    iterations: int = 7000
    sh_degree: int = 3
    sh_increase_every: int = 1000
    init_points: int = 20_000
    init_opacity: float = 0.1
    lr: LearningRates = field(default_factory=LearningRates)
    weights: LossWeights = field(default_factory=LossWeights)
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    densify: Strategy | None = field(default_factory=DensifyStrategy)
    mask_prune_views: int = 1
    lpips_weights: str | None = None
    lpips_net: str = "alex"
    chunk_elements: int | None = None
    seed: int = 0
    max_scale: float | None = None   # metres; caps every Gaussian's axes after each step
    thin: float | None = None        # metres: surfels on the visual hull's surface, this thin (needs masks)
    eps2d: float = EPS2D              # see rasterize(); the blur every splat gets, in pixels^2

    @classmethod
    def fast(cls, iterations: int = 400, **changes) -> "ObjectConfig":
        """Settings for short CPU runs on capture takes (hundreds of steps, not 3DGS's 30k): a fixed
        set of 3000 half-opaque Gaussians (no densification), SH degree 1 from the first step
        (enough for the view-dependent shading of matte surfaces), FAST_LR's steps, and no LPIPS
        term (FAST_LOSS)."""
        base = dict(iterations=iterations, sh_degree=1, sh_increase_every=1, init_points=3000,
                    init_opacity=0.5, densify=None, lr=FAST_LR, weights=FAST_LOSS)
        return cls(**{**base, **changes})

    @classmethod
    def surfels(cls, iterations: int = 400, **changes) -> "ObjectConfig":
        """`fast` with surfels for contacts: discs on the visual hull, at most SURFEL_MAX_SCALE_M
        wide and SURFEL_THIN_M thin, drawn with the small blur SURFACE_EPS2D, with the silhouette
        term (SURFEL_MASK_WEIGHT) and without the isotropy term (it keeps round Gaussians round
        and would fight the discs' shape)."""
        return cls.fast(iterations, **{**surfel_settings(), **changes})


def surfel_settings() -> dict:
    """The settings `surfels` configs share (ObjectConfig.surfels, HandConfig.surfels)."""
    return dict(weights=replace(FAST_LOSS, isotropy=0.0, mask=SURFEL_MASK_WEIGHT), max_scale=SURFEL_MAX_SCALE_M,
                thin=SURFEL_THIN_M, eps2d=SURFACE_EPS2D)


@dataclass
class TrainResult:
    gaussians: Gaussians
    history: list[dict[str, float]]
    scene_scale: float


def scene_frame(views: Views) -> tuple[torch.Tensor, float, float]:
    """(centre, half-size, camera extent) of the region all cameras look at.

    The centre is the point nearest to every optical axis (least squares); the half-size is the
    smallest half-width of any camera's field of view at that point; the camera extent is 1.1
    times the largest distance of a camera centre from the centres' mean (3DGS's scene scale).
    """
    c = views.centres.double().cpu()
    d = views.viewmats[:, 2, :3].double().cpu()  # optical axes: third row of R
    d = d / d.norm(dim=-1, keepdim=True)
    P = torch.eye(3, dtype=torch.float64) - d[:, :, None] * d[:, None, :]
    centre = torch.linalg.lstsq(P.sum(0), torch.einsum("vij,vj->i", P, c)).solution
    dist = (c - centre).norm(dim=-1)
    fov = torch.minimum(views.width / 2 / views.Ks[:, 0, 0], views.height / 2 / views.Ks[:, 1, 1]).double().cpu()
    half = float((dist * fov).min())
    extent = 1.1 * float((c - c.mean(0)).norm(dim=-1).max())
    return centre.float(), half, max(extent, 1e-6)


def in_hull(points: torch.Tensor, views: Views) -> torch.Tensor:
    """(N,) bool: points that no mask puts on the background and that at least half the views
    see (in front of the camera and inside the image, which may be a crop around the object)."""
    flat, seen = nearest_pixels(points, views.viewmats, views.Ks, views.height, views.width)
    if views.masks is None:
        return torch.ones(len(points), dtype=torch.bool, device=points.device)
    background = seen & ~views.masks.reshape(-1)[flat]
    return (background.sum(0) == 0) & (2 * seen.sum(0) >= len(views))


def hull_box(views: Views, levels: int = 3, resolution: int = 48) -> tuple[torch.Tensor, torch.Tensor]:
    """Corners (lo, hi) of a box around the visual hull of the masks.

    The object may fill a small part of the space the cameras see (an object on a table in a
    capture cube), where uniform sampling would almost never land inside it: a grid over the
    whole camera rig is carved, the box shrunk to the surviving cells (plus one cell), and that
    repeated at finer cells. Without masks: the cube all cameras see (scene_frame).
    """
    centre, half, extent = scene_frame(views)
    centre = centre.to(views.images.device)
    if views.masks is None:
        return centre - half, centre + half
    lo, hi = centre - max(half, extent), centre + max(half, extent)
    for _ in range(levels):
        axes = [torch.linspace(float(lo[i]), float(hi[i]), resolution, device=lo.device) for i in range(3)]
        grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
        inside = grid[in_hull(grid, views)]
        if len(inside) == 0:
            break
        cell = (hi - lo) / (resolution - 1)
        lo, hi = inside.min(0).values - cell, inside.max(0).values + cell
    return lo, hi


def object_scale(views: Views) -> float:
    """The scene scale of the learning rate of the means and of the densification thresholds.

    3DGS uses the cameras' extent, right when the scene fills the space between them; with
    masks it is the diagonal of the visual hull's box instead, as an object in a capture cube
    is a few centimetres across among cameras a metre apart.
    """
    if views.masks is None:
        return scene_frame(views)[2]
    lo, hi = hull_box(views)
    return max(float((hi - lo).norm()), 1e-6)


def init_points(views: Views, n: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """n points (and their mean colour over the views) in the visual hull of the masks.

    Candidates are drawn uniformly in hull_box and kept when they are in_hull; without masks
    every candidate in the cube all cameras see is kept.
    """
    lo, hi = hull_box(views)
    kept = []
    count = 0
    for _ in range(50):
        cand = lo + torch.rand(4 * n, 3, generator=generator).to(lo.device) * (hi - lo)
        cand = cand[in_hull(cand, views)]
        kept.append(cand)
        count += len(cand)
        if count >= n:
            break
    points = torch.cat(kept)[:n]
    if len(points) == 0:
        raise ValueError("no point lies inside every object mask: masks and cameras disagree")
    return points, mean_colour(points, views)


def hull_surface(views: Views, n: int, generator: torch.Generator, neighbours: int = 16
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """n points on the boundary of the masks' visual hull, their outward normals and mean colours.

    A point of the hull is on its boundary when a step of 2 % of the hull box's diagonal along
    some axis leaves the hull; its normal is the direction of least spread of its neighbours
    (PCA), turned to the side where a step leaves the hull (away from the hull's centre where
    both or neither side does), and the point is moved out along it onto the boundary."""
    if views.masks is None:
        raise ValueError("surfels on the visual hull need masks")
    lo, hi = hull_box(views)
    step = 0.02 * float((hi - lo).norm())
    axes = torch.cat([torch.eye(3), -torch.eye(3)]).to(lo.device) * step
    kept, count = [], 0
    for _ in range(100):
        cand = lo + torch.rand(20 * n, 3, generator=generator).to(lo.device) * (hi - lo)
        cand = cand[in_hull(cand, views)]
        leaves = ~in_hull((cand[:, None] + axes[None]).reshape(-1, 3), views).reshape(-1, 6)
        kept.append(cand[leaves.any(dim=1)])
        count += len(kept[-1])
        if count >= n:
            break
    points = torch.cat(kept)[:n]
    if len(points) <= neighbours:
        raise ValueError("the visual hull of the masks has no surface to put surfels on: masks and cameras disagree")
    p = points.double().cpu().numpy()
    _, idx = cKDTree(p).query(p, k=neighbours)
    spread = p[idx] - p[idx].mean(axis=1, keepdims=True)
    normals = torch.from_numpy(np.linalg.eigh(np.einsum("nki,nkj->nij", spread, spread))[1][:, :, 0])
    normals = normals.to(points.dtype).to(points.device)
    out_plus = ~in_hull(points + step * normals, views)
    out_minus = ~in_hull(points - step * normals, views)
    away = ((points - points.mean(0)) * normals).sum(-1) > 0
    outward = torch.where(out_plus != out_minus, out_plus, away)
    normals = torch.where(outward[:, None], normals, -normals)
    # out along the normal onto the boundary itself (bisection between inside and 2 steps out)
    inside = torch.zeros(len(points), dtype=points.dtype, device=points.device)
    outside = torch.full_like(inside, 2 * step)
    for _ in range(10):
        middle = (inside + outside) / 2
        still = in_hull(points + middle[:, None] * normals, views)
        inside, outside = torch.where(still, middle, inside), torch.where(still, outside, middle)
    points = points + inside[:, None] * normals
    return points, normals, mean_colour(points, views)


def mean_colour(points: torch.Tensor, views: Views) -> torch.Tensor:
    """Average image colour (N,3) at the projections of points (N,3) over the views that see them."""
    flat, seen = nearest_pixels(points, views.viewmats, views.Ks, views.height, views.width)
    rgb = views.images.reshape(-1, 3)[flat] * seen[..., None]
    return (rgb.sum(0) / seen.sum(0).clamp_min(1)[:, None]).clamp(0, 1)


def render(gaussians: Gaussians, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
           background: torch.Tensor, sh_degree: int | None = None, **kwargs):
    """Render a model into cameras with rasterize(); sh_degree defaults to the model's."""
    return rasterize(gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities, gaussians.sh,
                     viewmats, Ks, width, height, background=background,
                     sh_degree=gaussians.sh_degree if sh_degree is None else sh_degree, **kwargs)


@torch.no_grad()
def evaluate(gaussians: Gaussians, views: Views, background=(0.0, 0.0, 0.0),
             lpips: LPIPS | None = None, eps2d: float = EPS2D) -> dict[str, float]:
    """Mean scores of the model over held-out views: PSNR (dB) and SSIM of the whole image
    (with masks: the image composited on the background outside the mask, as trained), with
    masks also `psnr_mask`, the PSNR over the mask's pixels alone, and, with an LPIPS module, LPIPS.
    Render with the splat blur `eps2d` the model was trained with."""
    bg = torch.as_tensor(background, dtype=views.images.dtype, device=views.images.device)
    scores: dict[str, list[float]] = {"psnr": [], "ssim": [], "psnr_mask": [], "lpips": []}
    for i in range(len(views)):
        rgb, alpha = render(gaussians, views.viewmats[i:i + 1], views.Ks[i:i + 1], views.width, views.height, bg,
                            eps2d=eps2d)
        add_scores(scores, views.composite(rgb, alpha, bg, slice(i, i + 1)), views.subset([i]), bg, lpips)
    return {k: sum(v) / len(v) for k, v in scores.items() if v}


def add_scores(scores: dict[str, list[float]], rendered: torch.Tensor, views: "Views", background: torch.Tensor,
               lpips: LPIPS | None = None) -> None:
    """Append the scores (see evaluate) of renders (V,H,W,3) of `views` to the lists in `scores`; LPIPS
    only of views as large as its network takes (LPIPS.min_size)."""
    pred = rendered.clamp(0, 1).permute(0, 3, 1, 2)
    target = views.targets(background).permute(0, 3, 1, 2)
    for i in range(len(views)):
        p, t = pred[i:i + 1], target[i:i + 1]
        scores["psnr"].append(float(psnr(p, t)))
        scores["ssim"].append(float(ssim(p, t)))
        if views.masks is not None and bool(views.masks[i].any()):
            m = views.masks[i][None, None].expand_as(p)
            scores["psnr_mask"].append(float(psnr(p[m], t[m])))
        if lpips is not None and min(p.shape[-2:]) >= lpips.min_size:
            scores["lpips"].append(float(lpips(p, t).mean()))


def train_object(views: Views, config: ObjectConfig | None = None, init: Gaussians | None = None,
                 progress: Progress = silent) -> TrainResult:
    """Fit static Gaussians to calibrated views (with masks when given); see the module doc.
    Reports progress("object", step, iterations)."""
    cfg = config or ObjectConfig()
    gen = torch.Generator().manual_seed(cfg.seed)
    torch.manual_seed(cfg.seed)
    bg = torch.tensor(cfg.background, dtype=views.images.dtype, device=views.images.device)
    targets = views.targets(bg)
    scene_scale = object_scale(views)
    if init is None and cfg.thin is not None:
        points, normals, colours = hull_surface(views, cfg.init_points, gen)
        gaussians = Gaussians.surfels(points, normals, colours, cfg.sh_degree, cfg.init_opacity, cfg.thin)
    elif init is None:
        points, colours = init_points(views, cfg.init_points, gen)
        gaussians = Gaussians.from_points(points, colours, cfg.sh_degree, opacity=cfg.init_opacity)
    else:
        gaussians = init
    lpips = training_lpips(cfg.weights.lpips, cfg.lpips_weights, cfg.lpips_net, min(views.width, views.height),
                           views.images.device)
    optimizers = make_optimizers(gaussians, cfg.lr, scene_scale)
    densify = None if cfg.densify is None else Densification.start(cfg.densify, gaussians.params, optimizers,
                                                                   scene_scale)
    history = []
    order = torch.randperm(len(views), generator=gen)
    progress("object", 0, cfg.iterations)
    for step in range(1, cfg.iterations + 1):
        i = int(order[(step - 1) % len(views)])
        if step % len(views) == 0:
            order = torch.randperm(len(views), generator=gen)
        means_lr = decay_means_lr(optimizers["means"], cfg.lr, scene_scale, step, cfg.iterations)
        degree = min(cfg.sh_degree, step // cfg.sh_increase_every)
        rgb, alpha, info = render(gaussians, views.viewmats[i:i + 1], views.Ks[i:i + 1], views.width, views.height,
                                  bg, sh_degree=degree, return_meta=True, chunk_elements=cfg.chunk_elements,
                                  eps2d=cfg.eps2d)
        loss, parts = image_loss(views.composite(rgb, alpha, bg, slice(i, i + 1)), targets[i:i + 1],
                                 gaussians.scales, cfg.weights, lpips, alpha,
                                 None if views.masks is None else views.masks[i:i + 1])
        record = optimize_step(gaussians.params, optimizers, densify, loss, parts, info, step, means_lr)
        gaussians.cap_scales(cfg.max_scale, cfg.thin)
        if densify is not None and views.masks is not None and densify.refines_at(step):
            record["mask_pruned"] = prune_outside_masks(gaussians.params, optimizers, densify.state, views.viewmats,
                                                        views.Ks, views.masks, cfg.mask_prune_views)
        history.append(record)
        progress("object", step, cfg.iterations)
    return TrainResult(gaussians, history, scene_scale)
