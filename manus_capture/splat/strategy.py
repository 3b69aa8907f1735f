"""Adaptive density control of 3D Gaussian splatting, kept apart from rendering.

The strategy watches the screen-space gradients of the Gaussians' projected centres and, every
`refine_every` steps between `refine_start` and `refine_stop`:

- clones small Gaussians (largest scale <= grow_scale3d * scene_scale) whose mean gradient
  exceeds grow_grad2d: an exact copy joins the set (the two then drift apart under the optimizer);
- splits large ones with a high gradient into two children drawn from the parent's own
  distribution, each with the parent's scales divided by 1.6, and removes the parent;
- prunes Gaussians that became transparent (opacity < prune_opacity) and, after the first
  opacity reset, those larger than prune_scale3d * scene_scale;

and every `reset_every` steps it lowers all opacities to at most 2 * prune_opacity so that
Gaussians that are not needed fade out and get pruned. `prune_outside_masks` removes Gaussians
that project onto the background of object masks (floaters outside the visual hull).

Gradients are measured like 3DGS and gsplat (pixel gradients scaled by half the image size and
the number of cameras in the batch, i.e. in NDC units), so their thresholds carry over.
Every operation edits the Gaussians' parameters and the Adam moments together, row by row.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch

from .gaussians import Gaussians, quat_to_rotmat

SPLIT_SCALE_DIVISOR = 1.6


@dataclass
class DensifyStrategy:
    """Clone, split, prune and opacity reset (defaults of 3D Gaussian splatting)."""

    scene_scale: float = 1.0
    grow_grad2d: float = 0.0002
    grow_scale3d: float = 0.01
    prune_opacity: float = 0.005
    prune_scale3d: float = 0.1
    refine_start: int = 500
    refine_stop: int = 15_000
    refine_every: int = 100
    reset_every: int = 3000
    max_gaussians: int = 2_000_000

    def __post_init__(self) -> None:
        self._grad = None
        self._count = None

    # --- the training-loop hooks ------------------------------------------------------------

    def before_backward(self, meta: dict) -> None:
        """Ask autograd to keep the gradient of the projected centres (call before backward)."""
        if meta["means2d"].requires_grad:
            meta["means2d"].retain_grad()

    def after_backward(self, gaussians: Gaussians, optimizer: torch.optim.Optimizer, meta: dict,
                       step: int) -> dict[str, int]:
        """Accumulate statistics and refine when due; returns counts of what was done."""
        self._accumulate(len(gaussians), meta)
        done = {"cloned": 0, "split": 0, "pruned": 0, "reset": 0}
        if self.refine_start < step < self.refine_stop and step % self.refine_every == 0:
            done.update(self.refine(gaussians, optimizer, step))
        if step > 0 and step % self.reset_every == 0 and step < self.refine_stop:
            self.reset_opacity(gaussians, optimizer)
            done["reset"] = 1
        return done

    def _accumulate(self, n: int, meta: dict) -> None:
        grad = meta["means2d"].grad
        if self._grad is None or self._grad.shape[0] != n:
            self._grad = torch.zeros(n, device=meta["means2d"].device)
            self._count = torch.zeros(n, device=meta["means2d"].device)
        if grad is None:
            return
        scale = torch.tensor([meta["width"] / 2, meta["height"] / 2], device=grad.device) * meta["n_cameras"]
        norms = (grad.detach() * scale).norm(dim=-1)  # (C,N)
        visible = meta["visible"]
        self._grad += torch.where(visible, norms, 0).sum(0).to(self._grad.dtype)
        self._count += visible.sum(0).to(self._count.dtype)

    def refine(self, gaussians: Gaussians, optimizer: torch.optim.Optimizer, step: int) -> dict[str, int]:
        """One growth-and-prune round from the accumulated gradients."""
        if self._grad is None or self._grad.shape[0] != len(gaussians):
            return {}
        grad = self._grad / self._count.clamp_min(1)
        high = grad > self.grow_grad2d
        small = gaussians.scales.detach().amax(-1) <= self.grow_scale3d * self.scene_scale
        room = max(self.max_gaussians - len(gaussians), 0)
        if int(high.sum()) > room:  # each clone or split adds one Gaussian: keep the steepest
            steepest = torch.topk(torch.where(high, grad, -1.0), room).indices
            high = torch.zeros_like(high)
            high[steepest] = True
        to_clone = high & small
        to_split = high & ~small
        n_clone, n_split = int(to_clone.sum()), int(to_split.sum())
        self.clone(gaussians, optimizer, to_clone)
        # Clones were appended at the end, never split in the same round.
        self.split(gaussians, optimizer, torch.cat([to_split, to_split.new_zeros(n_clone)]))
        big = gaussians.scales.detach().amax(-1) > self.prune_scale3d * self.scene_scale
        prune = gaussians.opacities.detach() < self.prune_opacity
        if step > self.reset_every:
            prune = prune | big
        n_prune = int(prune.sum())
        self.prune(gaussians, optimizer, prune)
        self._grad = None
        return {"cloned": n_clone, "split": n_split, "pruned": n_prune}

    # --- the operations ------------------------------------------------------------------------

    def clone(self, gaussians: Gaussians, optimizer: torch.optim.Optimizer | None, mask: torch.Tensor) -> None:
        """Append an exact copy of every Gaussian in `mask`; the copies start with zero moments."""
        _edit(gaussians, optimizer, lambda name, p: torch.cat([p, p[mask]]),
              lambda s: torch.cat([s, torch.zeros_like(s[mask])]))

    def split(self, gaussians: Gaussians, optimizer: torch.optim.Optimizer | None, mask: torch.Tensor,
              generator: torch.Generator | None = None) -> None:
        """Replace every Gaussian in `mask` by two samples of itself with scales / 1.6."""
        k = int(mask.sum())
        if k == 0:
            return
        scales = gaussians.scales.detach()[mask]
        R = quat_to_rotmat(gaussians.quats.detach()[mask])
        noise = torch.randn(2, k, 3, generator=generator, dtype=scales.dtype).to(scales.device)
        offsets = torch.einsum("kij,bkj->bki", R, noise * scales).reshape(2 * k, 3)

        def child(name: str, p: torch.Tensor) -> torch.Tensor:
            parents = p[mask].repeat(2, *([1] * (p.dim() - 1)))
            if name == "means":
                parents = parents + offsets.to(p.dtype)
            elif name == "log_scales":
                parents = parents - math.log(SPLIT_SCALE_DIVISOR)
            return torch.cat([p[~mask], parents])

        _edit(gaussians, optimizer, child,
              lambda s: torch.cat([s[~mask], torch.zeros_like(s[mask]).repeat(2, *([1] * (s.dim() - 1)))]))

    def prune(self, gaussians: Gaussians, optimizer: torch.optim.Optimizer | None, mask: torch.Tensor) -> None:
        """Remove every Gaussian in `mask`."""
        if bool(mask.any()):
            _edit(gaussians, optimizer, lambda name, p: p[~mask], lambda s: s[~mask])

    def reset_opacity(self, gaussians: Gaussians, optimizer: torch.optim.Optimizer | None) -> None:
        """Lower every opacity to at most 2 * prune_opacity and forget its Adam moments."""
        value = 2 * self.prune_opacity
        logit = math.log(value / (1 - value))
        _edit(gaussians, optimizer, lambda name, p: p.clamp_max(logit) if name == "opacity_logits" else p,
              torch.zeros_like, only="opacity_logits")

    def prune_outside_masks(self, gaussians: Gaussians, optimizer: torch.optim.Optimizer | None,
                            viewmats: torch.Tensor, Ks: torch.Tensor, masks: torch.Tensor,
                            min_views: int = 1) -> int:
        """Remove Gaussians whose centre falls on the background of at least `min_views` masks.

        masks (V,H,W) bool, True on the object; a view counts only where the centre is in front of
        the camera and inside the image (pixel centres at integer coordinates). Returns how many
        Gaussians were removed.
        """
        outside = outside_mask_votes(gaussians.means.detach(), viewmats, Ks, masks) >= min_views
        self.prune(gaussians, optimizer, outside)
        return int(outside.sum())


def nearest_pixels(points: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor, height: int,
                   width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Where points (N,3) land in V views: flat indices (V,N) into (V,H,W) images of the pixel
    nearest to each projection, and (V,N) whether it is in front of the camera and in the image."""
    R, t = viewmats[:, :3, :3].to(points.dtype), viewmats[:, :3, 3].to(points.dtype)
    uvw = torch.einsum("vij,vnj->vni", Ks.to(points.dtype), torch.einsum("vij,nj->vni", R, points) + t[:, None])
    z = uvw[..., 2]
    front = z > 1e-9
    uv = torch.round(uvw[..., :2] / torch.where(front, z, torch.ones_like(z))[..., None]).long()
    inside = front & (uv[..., 0] >= 0) & (uv[..., 0] < width) & (uv[..., 1] >= 0) & (uv[..., 1] < height)
    row, col = uv[..., 1].clamp(0, height - 1), uv[..., 0].clamp(0, width - 1)
    view = torch.arange(len(viewmats), device=points.device)[:, None]
    return (view * height + row) * width + col, inside


def outside_mask_votes(points: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor,
                       masks: torch.Tensor) -> torch.Tensor:
    """For points (N,3): in how many of the V masks (V,H,W) each lands inside the image on background."""
    flat, inside = nearest_pixels(points, viewmats, Ks, masks.shape[1], masks.shape[2])
    return (inside & ~masks.reshape(-1)[flat]).sum(0)


def _edit(gaussians: Gaussians, optimizer: torch.optim.Optimizer | None,
          param_fn: Callable[[str, torch.Tensor], torch.Tensor],
          state_fn: Callable[[torch.Tensor], torch.Tensor], only: str | None = None) -> None:
    """Replace parameters by param_fn(name, old) and their per-row optimizer state by state_fn."""
    groups = {}
    if optimizer is not None:
        for group in optimizer.param_groups:
            for i, p in enumerate(group["params"]):
                groups[id(p)] = (group, i)
    for name in list(gaussians.params.keys()):
        if only is not None and name != only:
            continue
        old = gaussians.params[name]
        new = torch.nn.Parameter(param_fn(name, old.detach()), requires_grad=old.requires_grad)
        gaussians.params[name] = new
        if id(old) in groups:
            group, i = groups[id(old)]
            group["params"][i] = new
            state = optimizer.state.pop(old, None)
            if state:
                optimizer.state[new] = {k: state_fn(v) if torch.is_tensor(v) and v.shape == old.shape else v
                                        for k, v in state.items()}
