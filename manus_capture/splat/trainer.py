"""The object model: static Gaussians fitted to calibrated views with masks.

Inputs are plain tensors (`Views`): images (V,H,W,3) in [0,1], intrinsics K (V,3,3) in pixels,
world-to-camera rotations R (V,3,3) and translations t (V,3) as in CameraRig
(x_cam = R x + t), and optional object masks (V,H,W). Images are assumed undistorted.

With masks, the training target of a view is its image on the object and the background colour
elsewhere, so the model holds the object alone; Gaussians are initialized inside the visual hull
of the masks and, during densification, those projecting outside a mask are pruned.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field, replace

import torch

from .gaussians import PARAM_NAMES, Gaussians
from .losses import LPIPS, LossWeights, isotropy, l1, load_lpips, psnr, ssim
from .rasterize import rasterize
from .strategy import DensifyStrategy, nearest_pixels, outside_mask_votes


@dataclass
class Views:
    """Calibrated views: images (V,H,W,3) in [0,1], Ks (V,3,3), viewmats (V,4,4), masks (V,H,W) or None."""

    images: torch.Tensor
    Ks: torch.Tensor
    viewmats: torch.Tensor
    masks: torch.Tensor | None = None

    @classmethod
    def from_rig(cls, images: torch.Tensor, K: torch.Tensor, R: torch.Tensor, t: torch.Tensor,
                 masks: torch.Tensor | None = None) -> "Views":
        """Views from CameraRig-style K, R, t (any array type; float32 tensors are made)."""
        K, R, t = (torch.as_tensor(x, dtype=torch.float32) for x in (K, R, t))
        viewmats = torch.eye(4).repeat(len(K), 1, 1)
        viewmats[:, :3, :3] = R
        viewmats[:, :3, 3] = t
        images = torch.as_tensor(images, dtype=torch.float32)
        masks = None if masks is None else torch.as_tensor(masks, dtype=torch.bool)
        return cls(images, K, viewmats, masks)

    def __len__(self) -> int:
        return self.images.shape[0]

    def to(self, device: str | torch.device) -> "Views":
        return Views(self.images.to(device), self.Ks.to(device), self.viewmats.to(device),
                     None if self.masks is None else self.masks.to(device))

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
                     None if self.masks is None else self.masks[index])

    def targets(self, background: torch.Tensor) -> torch.Tensor:
        """Images with everything outside the masks set to the background colour."""
        if self.masks is None:
            return self.images
        return torch.where(self.masks[..., None], self.images, background.to(self.images.dtype))


@dataclass
class LearningRates:
    """Adam step sizes per parameter (3DGS defaults); means scale with the scene and decay."""

    means: float = 1.6e-4
    means_final: float = 1.6e-6
    quats: float = 1e-3
    log_scales: float = 5e-3
    opacity_logits: float = 5e-2
    sh0: float = 2.5e-3
    shN: float = 2.5e-3 / 20


@dataclass
class ObjectConfig:
    """Settings of `train_object`. densify=None keeps the number of Gaussians fixed."""

    iterations: int = 7000
    sh_degree: int = 3
    sh_increase_every: int = 1000
    init_points: int = 20_000
    init_opacity: float = 0.1
    lr: LearningRates = field(default_factory=LearningRates)
    weights: LossWeights = field(default_factory=LossWeights)
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    densify: DensifyStrategy | None = field(default_factory=DensifyStrategy)
    mask_prune_views: int = 1
    lpips_weights: str | None = None
    lpips_net: str = "alex"
    chunk_elements: int | None = None
    seed: int = 0


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


def init_points(views: Views, n: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """n points (and their mean colour over the views) in the visual hull of the masks.

    Candidates are drawn uniformly in the cube all cameras see and kept when every view that
    sees them puts them on the object; without masks every candidate is kept.
    """
    centre, half, _ = scene_frame(views)
    kept = []
    count = 0
    for _ in range(50):
        cand = (centre + (torch.rand(4 * n, 3, generator=generator) * 2 - 1) * half).to(views.images.device)
        if views.masks is not None:
            cand = cand[outside_mask_votes(cand, views.viewmats, views.Ks, views.masks) == 0]
        kept.append(cand)
        count += len(cand)
        if count >= n:
            break
    points = torch.cat(kept)[:n]
    if len(points) == 0:
        raise ValueError("no point lies inside every object mask: masks and cameras disagree")
    return points, mean_colour(points, views)


def mean_colour(points: torch.Tensor, views: Views) -> torch.Tensor:
    """Average image colour (N,3) at the projections of points (N,3) over the views that see them."""
    flat, seen = nearest_pixels(points, views.viewmats, views.Ks, views.height, views.width)
    rgb = views.images.reshape(-1, 3)[flat] * seen[..., None]
    return (rgb.sum(0) / seen.sum(0).clamp_min(1)[:, None]).clamp(0, 1)


def make_optimizer(gaussians: Gaussians, lr: LearningRates, scene_scale: float,
                   extra: list[dict] | None = None) -> torch.optim.Adam:
    """Adam with one parameter group per Gaussian parameter (named), plus `extra` groups."""
    groups = [{"params": [gaussians.params[name]], "name": name,
               "lr": getattr(lr, name) * (scene_scale if name == "means" else 1.0)} for name in PARAM_NAMES]
    return torch.optim.Adam(groups + (extra or []), eps=1e-15)


def decay_means_lr(optimizer: torch.optim.Optimizer, lr: LearningRates, scene_scale: float,
                   step: int, total: int) -> None:
    """Exponential decay of the means' step size from lr.means to lr.means_final (times scale)."""
    frac = min(step / max(total, 1), 1.0)
    value = scene_scale * math.exp((1 - frac) * math.log(lr.means) + frac * math.log(lr.means_final))
    for group in optimizer.param_groups:
        if group.get("name") == "means":
            group["lr"] = value


def image_loss(pred: torch.Tensor, target: torch.Tensor, scales: torch.Tensor, weights: LossWeights,
               lpips: LPIPS | None) -> tuple[torch.Tensor, dict[str, float]]:
    """Weighted L1 + (1 - SSIM) + LPIPS + isotropy of rendered (C,H,W,3) against target images."""
    p, t = pred.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2)
    parts = {"l1": l1(p, t), "ssim": 1 - ssim(p, t), "isotropy": isotropy(scales)}
    if lpips is not None:
        parts["lpips"] = lpips(p, t).mean()
    loss = sum(getattr(weights, k) * v for k, v in parts.items())
    return loss, {k: float(v.detach()) for k, v in parts.items()}


def optimize_step(gaussians: Gaussians, optimizer: torch.optim.Optimizer, strategy: DensifyStrategy | None,
                  loss: torch.Tensor, parts: dict[str, float], meta: dict, step: int) -> dict[str, float]:
    """Backward, Adam step and densification of one training step; returns the step's record."""
    if strategy is not None:
        strategy.before_backward(meta)
    loss.backward()
    optimizer.step()
    optimizer.zero_grad(set_to_none=True)
    record = {"step": step, "loss": float(loss.detach()), "n": len(gaussians), **parts}
    if strategy is not None:
        record.update(strategy.after_backward(gaussians, optimizer, meta, step))
    return record


def render(gaussians: Gaussians, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
           background: torch.Tensor, sh_degree: int | None = None, **kwargs):
    """Render a model into cameras with rasterize(); sh_degree defaults to the model's."""
    return rasterize(gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities, gaussians.sh,
                     viewmats, Ks, width, height, background=background,
                     sh_degree=gaussians.sh_degree if sh_degree is None else sh_degree, **kwargs)


@torch.no_grad()
def evaluate(gaussians: Gaussians, views: Views, background=(0.0, 0.0, 0.0),
             lpips: LPIPS | None = None) -> dict[str, float]:
    """Mean PSNR (dB), SSIM and, with an LPIPS module, LPIPS of the model over held-out views."""
    bg = torch.as_tensor(background, dtype=views.images.dtype, device=views.images.device)
    targets = views.targets(bg)
    scores: dict[str, list[float]] = {"psnr": [], "ssim": [], "lpips": []}
    for i in range(len(views)):
        rgb, _ = render(gaussians, views.viewmats[i:i + 1], views.Ks[i:i + 1], views.width, views.height, bg)
        p, t = rgb.clamp(0, 1).permute(0, 3, 1, 2), targets[i:i + 1].permute(0, 3, 1, 2)
        scores["psnr"].append(float(psnr(p, t)))
        scores["ssim"].append(float(ssim(p, t)))
        if lpips is not None:
            scores["lpips"].append(float(lpips(p, t).mean()))
    return {k: sum(v) / len(v) for k, v in scores.items() if v}


def train_object(views: Views, config: ObjectConfig | None = None, init: Gaussians | None = None,
                 progress: bool = True) -> TrainResult:
    """Fit static Gaussians to calibrated views (with masks when given); see the module doc."""
    from tqdm import tqdm

    cfg = config or ObjectConfig()
    gen = torch.Generator().manual_seed(cfg.seed)
    torch.manual_seed(cfg.seed)
    bg = torch.tensor(cfg.background, dtype=views.images.dtype, device=views.images.device)
    targets = views.targets(bg)
    _, _, scene_scale = scene_frame(views)
    if init is None:
        points, colours = init_points(views, cfg.init_points, gen)
        gaussians = Gaussians.from_points(points, colours, cfg.sh_degree, opacity=cfg.init_opacity)
    else:
        gaussians = init
    lpips = load_lpips(cfg.lpips_weights, cfg.lpips_net) if cfg.weights.lpips > 0 else None
    if lpips is not None:
        lpips = lpips.to(views.images.device)
    optimizer = make_optimizer(gaussians, cfg.lr, scene_scale)
    strategy = None if cfg.densify is None else replace(cfg.densify, scene_scale=scene_scale)

    history = []
    order = torch.randperm(len(views), generator=gen)
    bar = tqdm(range(1, cfg.iterations + 1), desc="object", unit="it", file=sys.stderr, disable=not progress)
    for step in bar:
        i = int(order[(step - 1) % len(views)])
        if step % len(views) == 0:
            order = torch.randperm(len(views), generator=gen)
        decay_means_lr(optimizer, cfg.lr, scene_scale, step, cfg.iterations)
        degree = min(cfg.sh_degree, step // cfg.sh_increase_every)
        rgb, _, meta = render(gaussians, views.viewmats[i:i + 1], views.Ks[i:i + 1], views.width, views.height,
                              bg, sh_degree=degree, return_meta=True, chunk_elements=cfg.chunk_elements)
        loss, parts = image_loss(rgb, targets[i:i + 1], gaussians.scales, cfg.weights, lpips)
        record = optimize_step(gaussians, optimizer, strategy, loss, parts, meta, step)
        if strategy is not None:
            due = strategy.refine_start < step < strategy.refine_stop and step % strategy.refine_every == 0
            if due and views.masks is not None:
                record["mask_pruned"] = strategy.prune_outside_masks(
                    gaussians, optimizer, views.viewmats, views.Ks, views.masks, cfg.mask_prune_views)
        history.append(record)
        if step % 10 == 0 or step == cfg.iterations:
            bar.set_postfix(loss=f"{record['loss']:.4f}", n=len(gaussians))
    return TrainResult(gaussians, history, scene_scale)
