"""MANUS-Hand: articulated 3D Gaussians of a hand, posed by the 26-DOF skeleton.

The model lives in the canonical (rest) frame of manus_core.skeleton:

- canonical Gaussians, initialized around every bone: a normal distribution centred at the
  bone's midpoint, spread by the bone's length (`spread` times the length along the bone, at
  most `radius` across it, as fingers are thinner than they are long); or, for contacts, surfels
  on a given surface such as the capsule template's (`on_surface`, see trainer.ObjectConfig.surfels);
- skinning weights on a canonical voxel grid (20 bones x G^3), initialized one-hot from the
  nearest bone of each voxel centre, smoothed by a few 3x3x3 box filters and kept only for
  bones that share a joint with the nearest one (fingers never blend); a Gaussian's
  weights are sampled trilinearly at its canonical centre and renormalized to sum to one, so
  they follow the Gaussians through densification without per-Gaussian bookkeeping;
- posing: the skeleton's forward kinematics gives every bone's rigid motion (R_b, t_b); linear
  blend skinning moves a centre to A x + sum_b w_b t_b with A = sum_b w_b R_b, and the
  covariance becomes A Sigma A^T (the blended rotation; exactly a rotation when one bone owns
  the Gaussian);
- colour: view directions are taken back to the canonical frame (A^T d) before the spherical
  harmonics are evaluated, so the colour sticks to the hand's surface rather than to the world.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from manus_core.progress import Progress, silent
from manus_core.skeleton import BONES, HandSkeleton

from .gaussians import Gaussians
from .losses import LPIPS, LossWeights, image_loss, training_lpips
from .optimize import Densification, LearningRates, Strategy, decay_means_lr, make_optimizers, optimize_step
from .rasterize import EPS2D, rasterize
from .sh import eval_sh
from .strategy import DensifyStrategy
from .trainer import FAST_LOSS, FAST_LR, Views, add_scores, surfel_settings

N_BONES = 20


def point_segment_distance(points: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Distances (N,S) from points (N,3) to segments a (S,3) -> b (S,3)."""
    ab = b - a
    t = ((points[:, None, :] - a[None]) * ab[None]).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-12)
    closest = a[None] + t.clamp(0, 1)[..., None] * ab[None]
    return (points[:, None, :] - closest).norm(dim=-1)


def bone_neighbours() -> torch.Tensor:
    """(20,20) bool: bones that share a joint (a bone is its own neighbour).

    Skinning only ever blends a bone with its neighbours: blending two fingers, which move
    independently, would tear the Gaussians between them apart.
    """
    bones = torch.as_tensor(BONES, dtype=torch.long)
    ends = bones[:, None, :, None] == bones[None, :, None, :]  # (20,20,2,2)
    return ends.flatten(2).any(-1)


def nearest_bone_grid(joints: torch.Tensor, grid_min: torch.Tensor, grid_max: torch.Tensor, resolution: int,
                      smooth: int = 2) -> torch.Tensor:
    """Skinning weights (20,G,G,G) indexed [bone, z, y, x] from the rest joints (21,3).

    One-hot on each voxel centre's nearest bone, smoothed by `smooth` 3x3x3 box filters, then
    restricted to the nearest bone's neighbours and normalized.
    """
    axes = [torch.linspace(float(grid_min[i]), float(grid_max[i]), resolution, dtype=joints.dtype) for i in range(3)]
    z, y, x = torch.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    centres = torch.stack([x, y, z], dim=-1).reshape(-1, 3)
    bones = torch.as_tensor(BONES, dtype=torch.long)
    nearest = point_segment_distance(centres, joints[bones[:, 0]], joints[bones[:, 1]]).argmin(dim=1)
    grid = F.one_hot(nearest, N_BONES).T.to(joints.dtype).reshape(1, N_BONES, resolution, resolution, resolution)
    box = torch.full((N_BONES, 1, 3, 3, 3), 1 / 27, dtype=joints.dtype)
    for _ in range(smooth):
        grid = F.conv3d(F.pad(grid, (1,) * 6, mode="replicate"), box, groups=N_BONES)
    allowed = bone_neighbours()[nearest].T.reshape(N_BONES, resolution, resolution, resolution)
    grid = grid[0] * allowed
    return grid / grid.sum(0, keepdim=True).clamp_min(1e-12)


def sample_around_bones(joints: torch.Tensor, per_bone: int, spread: float, radius: float, margin: float,
                        generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """per_bone points around each bone's midpoint: (points (20*per_bone,3), bone (20*per_bone,)).

    Normal with a standard deviation of spread * length along the bone and min(spread * length,
    radius) across it, truncated at two standard deviations; a sample is drawn again when it
    lies closer than `margin` to being nearer another finger's bone than its own, so no
    Gaussian starts where the skinning weights of two independent fingers meet.
    """
    bones = torch.as_tensor(BONES, dtype=torch.long)
    a, b = joints[bones[:, 0]], joints[bones[:, 1]]
    axis = b - a
    length = axis.norm(dim=-1, keepdim=True)
    u = axis / length
    helper = torch.where(u[:, 2:3].abs() < 0.9, torch.tensor([0.0, 0.0, 1.0]), torch.tensor([1.0, 0.0, 0.0]))
    v = torch.linalg.cross(u, helper)
    v = v / v.norm(dim=-1, keepdim=True)
    w = torch.linalg.cross(u, v)
    sd = torch.cat([spread * length, (spread * length).clamp_max(radius).expand(-1, 2)], dim=-1)  # (20,3)
    frame = torch.stack([u, v, w], dim=-1)  # columns: along, across, across
    foreign = ~bone_neighbours()
    points = torch.empty(N_BONES, per_bone, 3)
    todo = torch.ones(N_BONES, per_bone, dtype=torch.bool)
    for _ in range(100):
        k = int(todo.sum())
        if k == 0:
            break
        owner = torch.nonzero(todo)[:, 0]
        z = torch.randn(k, 3, generator=generator)
        p = (a[owner] + b[owner]) / 2 + torch.einsum("kij,kj->ki", frame[owner], z * sd[owner])
        d = point_segment_distance(p, a, b)  # (k,20)
        own = d.gather(1, owner[:, None])[:, 0]
        other = torch.where(foreign[owner], d, torch.inf).amin(dim=1)
        ok = (z.norm(dim=-1) <= 2.0) & (own + margin <= other)
        idx = torch.nonzero(todo)
        points[idx[ok, 0], idx[ok, 1]] = p[ok]
        todo[idx[ok, 0], idx[ok, 1]] = False
    if bool(todo.any()):
        raise ValueError("could not place the hand's Gaussians: bones too close for the requested spread")
    return points.reshape(-1, 3), torch.arange(N_BONES).repeat_interleave(per_bone)


class HandGaussians(torch.nn.Module):
    """Canonical Gaussians, a skinning-weight grid and the skeleton that poses them."""

    def __init__(self, gaussians: Gaussians, skin_grid: torch.Tensor, grid_min: torch.Tensor,
                 grid_max: torch.Tensor, bone_lengths=None) -> None:
        super().__init__()
        self.gaussians = gaussians
        self.skin_grid = torch.nn.Parameter(skin_grid.detach().clone())
        self.register_buffer("grid_min", torch.as_tensor(grid_min, dtype=skin_grid.dtype).clone())
        self.register_buffer("grid_max", torch.as_tensor(grid_max, dtype=skin_grid.dtype).clone())
        self.skeleton = HandSkeleton(bone_lengths)

    @classmethod
    def initialize(cls, bone_lengths=None, per_bone: int = 200, spread: float = 0.25, radius: float = 0.007,
                   margin: float = 0.006, sh_degree: int = 3, resolution: int = 64, padding: float = 0.02,
                   smooth: int = 2, colour=(0.8, 0.6, 0.5), opacity: float = 0.5,
                   seed: int = 0) -> "HandGaussians":
        """A fresh model around the rest skeleton (see sample_around_bones and nearest_bone_grid);
        lengths in metres. `margin` should exceed the grid's voxel diagonal (about 5 mm at the
        default resolution), or trilinear sampling blends two fingers at their boundary."""
        skeleton = HandSkeleton(bone_lengths)
        joints = torch.as_tensor(skeleton.rest_joints(), dtype=torch.float32)
        gen = torch.Generator().manual_seed(seed)
        means, _ = sample_around_bones(joints, per_bone, spread, radius, margin, gen)
        colours = torch.tensor(colour, dtype=torch.float32).expand(len(means), 3)
        gaussians = Gaussians.from_points(means, colours, sh_degree, opacity=opacity)
        return cls._with_grid(gaussians, skeleton, joints, resolution, padding, smooth)

    @classmethod
    def on_surface(cls, bone_lengths, points, normals, bones, thin: float, margin: float = 0.004,
                   sh_degree: int = 3, resolution: int = 64, padding: float = 0.02, smooth: int = 2,
                   colour=(0.8, 0.6, 0.5), opacity: float = 0.5) -> "HandGaussians":
        """A fresh model of surfels (Gaussians.surfels) on a given rest-pose surface: points (N,3)
        with outward normals (N,3), each on bone `bones` (N,), e.g. a capsule template's. Points
        closer than `margin` to being nearer another finger's bone than their own are left out, as
        in sample_around_bones."""
        skeleton = HandSkeleton(bone_lengths)
        joints = torch.as_tensor(skeleton.rest_joints(), dtype=torch.float32)
        points = torch.as_tensor(np.asarray(points), dtype=torch.float32)
        normals = torch.as_tensor(np.asarray(normals), dtype=torch.float32)
        bones = torch.as_tensor(np.asarray(bones), dtype=torch.long)
        ends = torch.as_tensor(BONES, dtype=torch.long)
        d = point_segment_distance(points, joints[ends[:, 0]], joints[ends[:, 1]])
        own = d.gather(1, bones[:, None])[:, 0]
        other = torch.where((~bone_neighbours())[bones], d, torch.inf).amin(dim=1)
        keep = own + margin <= other
        colours = torch.tensor(colour, dtype=torch.float32).expand(int(keep.sum()), 3)
        gaussians = Gaussians.surfels(points[keep], normals[keep], colours, sh_degree, opacity, thin)
        return cls._with_grid(gaussians, skeleton, joints, resolution, padding, smooth)

    @classmethod
    def _with_grid(cls, gaussians: Gaussians, skeleton: HandSkeleton, joints: torch.Tensor, resolution: int,
                   padding: float, smooth: int) -> "HandGaussians":
        means = gaussians.means.detach()
        lo = torch.minimum(means.min(0).values, joints.min(0).values) - padding
        hi = torch.maximum(means.max(0).values, joints.max(0).values) + padding
        grid = nearest_bone_grid(joints, lo, hi, resolution, smooth)
        return cls(gaussians, grid, lo, hi, skeleton.bone_lengths)

    def __len__(self) -> int:
        return len(self.gaussians)

    @property
    def opacities(self) -> torch.Tensor:
        return self.gaussians.opacities

    def pose_batch(self, angles: torch.Tensor) -> torch.Tensor:
        """Posed centres (T,N,3) for angles (T,26): pose()'s means for many poses at once."""
        g = self.gaussians
        angles = torch.as_tensor(angles, dtype=g.means.dtype, device=g.means.device)
        R, t = self.skeleton.bone_transforms(angles)  # (T,20,3,3), (T,20,3)
        w = self.skinning_weights()
        return torch.einsum("nb,tbij,nj->tni", w, R.to(w.dtype), g.means) + torch.einsum("nb,tbj->tnj", w, t.to(w.dtype))

    def skinning_weights(self, points: torch.Tensor | None = None) -> torch.Tensor:
        """Weights (N,20) at canonical points (default: the Gaussians' centres), summing to one."""
        points = self.gaussians.means if points is None else points
        # Trilinear interpolation as grid_sample's (align_corners, border padding: the point clamped
        # into the grid; x runs along the grid's last axis), written out: grid_sample on the CPU
        # and its backward took a sixth of a training step, the eight corners' gather a fraction.
        G = self.skin_grid.shape[-1]
        u = ((points - self.grid_min) / (self.grid_max - self.grid_min) * (G - 1)).clamp(0, G - 1)
        lo = u.detach().floor().clamp_max(G - 2)
        f = (u - lo).to(self.skin_grid.dtype)  # (N,3) within the cell
        x, y, z = lo.long().unbind(-1)
        corners = torch.tensor([(dx, dy, dz) for dz in (0, 1) for dy in (0, 1) for dx in (0, 1)], device=u.device)
        cx, cy, cz = corners.unbind(-1)
        index = ((z + cz[:, None]) * G + y + cy[:, None]) * G + x + cx[:, None]  # (8,N)
        share = torch.where(corners[:, None, :] == 1, f, 1 - f).prod(-1)  # (8,N)
        values = self.skin_grid.reshape(N_BONES, -1).index_select(1, index.reshape(-1)).clamp_min(0)
        w = (values.reshape(N_BONES, 8, -1) * share).sum(1).T  # (N,20)
        return w / w.sum(-1, keepdim=True).clamp_min(1e-8)

    def pose(self, angles: torch.Tensor) -> dict[str, torch.Tensor]:
        """Posed centres (N,3), covariances (N,3,3), blended linear maps A (N,3,3) and weights (N,20)
        for angles (26,); for angles (T,26) one of each per pose: (T,N,3), (T,N,3,3), (T,N,3,3)."""
        g = self.gaussians
        angles = torch.as_tensor(angles, dtype=g.means.dtype, device=g.means.device)
        R, t = self.skeleton.bone_transforms(angles)  # (...,20,3,3), (...,20,3)
        w = self.skinning_weights()
        A = torch.einsum("nb,...bij->...nij", w, R.to(w.dtype))
        means = torch.einsum("...nij,nj->...ni", A, g.means) + torch.einsum("nb,...bj->...nj", w, t.to(w.dtype))
        covars = A @ g.covariances() @ A.transpose(-1, -2)
        return {"means": means, "covars": covars, "A": A, "weights": w}

    def render(self, angles: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
               background: torch.Tensor | None = None, sh_degree: int | None = None, **kwargs):
        """rasterize() of the hand posed by `angles` into C cameras: (26,) one pose seen by every
        camera, or (C,26) one pose per camera."""
        return self.render_posed(self.pose(angles), viewmats, Ks, width, height, background, sh_degree, **kwargs)

    def render_posed(self, posed: dict[str, torch.Tensor], viewmats: torch.Tensor, Ks: torch.Tensor, width: int,
                     height: int, background: torch.Tensor | None = None, sh_degree: int | None = None, **kwargs):
        """rasterize() of a pose() result: one pose for every camera ((N,...) tensors) or one per
        camera ((C,N,...)), e.g. the frames of a take each in its own views, in one call."""
        g = self.gaussians
        C = len(viewmats)
        R, t = viewmats[:, :3, :3], viewmats[:, :3, 3]
        centres = -torch.einsum("cji,cj->ci", R, t)
        means = posed["means"] if posed["means"].dim() == 3 else posed["means"][None]
        A = posed["A"] if posed["A"].dim() == 4 else posed["A"][None]
        dirs = torch.einsum("cnji,cnj->cni", A.expand(C, -1, -1, -1), means - centres[:, None])  # A^T d: canonical
        colours = eval_sh(g.sh_degree if sh_degree is None else sh_degree, g.sh[None].expand(C, -1, -1, -1), dirs)
        return rasterize(posed["means"], None, None, g.opacities, colours, viewmats, Ks, width, height,
                         background=background, covars=posed["covars"], **kwargs)

    def extra_tensors(self) -> dict[str, torch.Tensor]:
        """What a checkpoint stores beside the Gaussians (see checkpoint.py)."""
        return {"skin_grid": self.skin_grid.detach(), "grid_min": self.grid_min, "grid_max": self.grid_max,
                "bone_lengths": torch.as_tensor(self.skeleton.bone_lengths, dtype=torch.float32)}

    @classmethod
    def from_checkpoint(cls, gaussians: Gaussians, extra: dict[str, torch.Tensor]) -> "HandGaussians":
        return cls(gaussians, extra["skin_grid"], extra["grid_min"], extra["grid_max"],
                   extra["bone_lengths"].double().numpy())


@dataclass
class HandConfig:
    """Settings of `train_hand`; densify as ObjectConfig's."""

    iterations: int = 10_000
    sh_degree: int = 3
    sh_increase_every: int = 1000
    lr: LearningRates = field(default_factory=lambda: LearningRates(means=1.6e-4, means_final=1.6e-6))
    skin_lr: float = 1e-3
    weights: LossWeights = field(default_factory=LossWeights)
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    densify: Strategy | None = field(default_factory=DensifyStrategy)
    lpips_weights: str | None = None
    lpips_net: str = "alex"
    chunk_elements: int | None = None
    seed: int = 0
    max_scale: float | None = None   # metres; caps every Gaussian's axes after each step
    thin: float | None = None        # metres; caps the third axis (surfels, HandGaussians.on_surface)
    eps2d: float = EPS2D              # see rasterize(); the blur every splat gets, in pixels^2

    @classmethod
    def fast(cls, iterations: int = 400, **changes) -> "HandConfig":
        """Settings for short CPU runs on capture takes (see ObjectConfig.fast): the initial
        Gaussians only, the initial skinning weights, SH degree 1 from the first step, FAST_LR's steps,
        no LPIPS term (FAST_LOSS)."""
        base = dict(iterations=iterations, sh_degree=1, sh_increase_every=1, densify=None, skin_lr=0.0, lr=FAST_LR,
                    weights=FAST_LOSS)
        return cls(**{**base, **changes})

    @classmethod
    def surfels(cls, iterations: int = 400, **changes) -> "HandConfig":
        """`fast` for a model of surfels (HandGaussians.on_surface): see ObjectConfig.surfels."""
        return cls.fast(iterations, **{**surfel_settings(), **changes})


def train_hand(model: HandGaussians, poses: torch.Tensor, views: list[Views], config: HandConfig | None = None,
               progress: Progress = silent) -> list[dict[str, float]]:
    """Fit a MANUS-Hand model to views of the hand in several poses; returns the loss history.

    poses (P,26) joint angles; views[p] the calibrated images (with hand masks when known) of
    pose p (poses without views are passed over). Every step renders one view of one pose. The
    model is changed in place. Reports progress("hand", step, iterations).
    """
    cfg = config or HandConfig()
    gen = torch.Generator().manual_seed(cfg.seed)
    bg = torch.tensor(cfg.background, dtype=torch.float32, device=model.gaussians.means.device)
    targets = [v.targets(bg) for v in views]
    scene_scale = float(model.skeleton.bone_lengths.sum() / 5)  # about one finger's length
    lpips = training_lpips(cfg.weights.lpips, cfg.lpips_weights, cfg.lpips_net,
                           min((min(v.width, v.height) for v in views if len(v)), default=0), bg.device)
    # skin_lr = 0 keeps the initial weights (and saves the Adam update of the whole grid).
    model.skin_grid.requires_grad_(cfg.skin_lr > 0)
    gaussian_optimizers = make_optimizers(model.gaussians, cfg.lr, scene_scale)
    optimizers = dict(gaussian_optimizers)
    if cfg.skin_lr > 0:  # the grid is no Gaussian parameter: no strategy sees its optimizer
        optimizers["skin_grid"] = torch.optim.Adam([{"params": [model.skin_grid], "name": "skin_grid",
                                                     "lr": cfg.skin_lr}], eps=1e-15)
    densify = None if cfg.densify is None else Densification.start(cfg.densify, model.gaussians.params,
                                                                   gaussian_optimizers, scene_scale)
    history = []
    usable = [i for i, v in enumerate(views) if len(v)]
    if not usable:
        raise ValueError("train_hand: no pose has a view")
    progress("hand", 0, cfg.iterations)
    for step in range(1, cfg.iterations + 1):
        p = usable[int(torch.randint(len(usable), (1,), generator=gen))]
        v = int(torch.randint(len(views[p]), (1,), generator=gen))
        means_lr = decay_means_lr(optimizers["means"], cfg.lr, scene_scale, step, cfg.iterations)
        degree = min(cfg.sh_degree, step // cfg.sh_increase_every)
        view = views[p]
        rgb, alpha, info = model.render(poses[p], view.viewmats[v:v + 1], view.Ks[v:v + 1], view.width,
                                        view.height, bg, sh_degree=degree, return_meta=True,
                                        chunk_elements=cfg.chunk_elements, eps2d=cfg.eps2d)
        loss, parts = image_loss(view.composite(rgb, alpha, bg, slice(v, v + 1)), targets[p][v:v + 1],
                                 model.gaussians.scales, cfg.weights, lpips, alpha,
                                 None if view.masks is None else view.masks[v:v + 1])
        history.append(optimize_step(model.gaussians.params, optimizers, densify, loss, parts, info, step, means_lr))
        # small splats cannot stand for the hand from inside it: to cover the silhouettes their
        # centres must stay on the surface, where contact is measured
        model.gaussians.cap_scales(cfg.max_scale, cfg.thin)
        progress("hand", step, cfg.iterations)
    return history


@torch.no_grad()
def evaluate_hand(model: HandGaussians, poses: torch.Tensor, views: list[Views],
                  background=(0.0, 0.0, 0.0), eps2d: float = EPS2D, lpips: LPIPS | None = None) -> dict[str, float]:
    """Mean PSNR (dB), SSIM, with masks psnr_mask and with an LPIPS module LPIPS (see
    trainer.evaluate) over every view of every given pose, rendered with the splat blur `eps2d`
    the model was trained with."""
    bg = torch.tensor(background, dtype=torch.float32, device=model.gaussians.means.device)
    scores: dict[str, list[float]] = {"psnr": [], "ssim": [], "psnr_mask": [], "lpips": []}
    for p, view in enumerate(views):
        if not len(view):
            continue
        rgb, alpha = model.render(poses[p], view.viewmats, view.Ks, view.width, view.height, bg, eps2d=eps2d)
        add_scores(scores, view.composite(rgb, alpha, bg), view, bg, lpips)
    return {k: sum(v) / len(v) for k, v in scores.items() if v}


def random_poses(n: int, skeleton: HandSkeleton, generator: torch.Generator, rotation: float = math.pi,
                 translation: float = 0.1) -> torch.Tensor:
    """n poses (n,26) uniform within the skeleton's joint limits, with a random global rotation
    (angle up to `rotation`) and translation (up to `translation` metres per axis)."""
    lo = torch.as_tensor(np.where(np.isfinite(skeleton.lower), skeleton.lower, 0.0), dtype=torch.float32)
    hi = torch.as_tensor(np.where(np.isfinite(skeleton.upper), skeleton.upper, 0.0), dtype=torch.float32)
    angles = lo + (hi - lo) * torch.rand(n, 26, generator=generator)
    axis = torch.randn(n, 3, generator=generator)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angles[:, 0:3] = axis * rotation * torch.rand(n, 1, generator=generator)
    angles[:, 3:6] = (torch.rand(n, 3, generator=generator) * 2 - 1) * translation
    return angles
