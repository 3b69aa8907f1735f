"""Adaptive density control of 3D Gaussian splatting, with gsplat's strategy API.

`DensifyStrategy` watches the screen-space gradients of the Gaussians' projected centres and,
every `refine_every` steps between `refine_start_iter` and `refine_stop_iter`:

- clones small Gaussians (largest scale <= grow_scale3d * scene_scale) whose mean gradient
  exceeds grow_grad2d: an exact copy joins the set (the two then drift apart under the optimizer);
- splits large ones with a high gradient into two children drawn from the parent's own
  distribution, each with the parent's scales divided by 1.6, and removes the parent;
- prunes Gaussians that became transparent (opacity < prune_opa) and, after the first opacity
  reset, those larger than prune_scale3d * scene_scale;

and every `reset_every` steps it lowers all opacities to at most 2 * prune_opa so that Gaussians
that are not needed fade out and get pruned. `prune_outside_masks` removes Gaussians that project
onto the background of object masks (floaters outside the visual hull).

The API, the settings' names and the gradient measure are those of gsplat's strategies
(gsplat.strategy.DefaultStrategy), so that gsplat's own strategies can drive the trainers too
(optimize.Densification):

    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=...)
    every step: strategy.step_pre_backward(params, optimizers, state, step, info)
                loss.backward(); every optimizer steps
                strategy.step_post_backward(params, optimizers, state, step, info, packed=False)

`params` maps "means", "quats", "scales" (logarithms), "opacities" (logits), "sh0" and "shN" to
parameters of N rows (Gaussians.params); `optimizers` maps the same names to optimizers of one
parameter each; `info` is rasterize()'s meta. The strategy object holds its settings only: what it
learns between steps lives in the plain dict `state`. Every operation below edits the parameters,
their Adam moments and the per-Gaussian rows of the state together.

Gradients are measured like 3DGS and gsplat (pixel gradients scaled by half the image size and
the number of cameras in the batch, i.e. in NDC units), so their thresholds carry over.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, MutableMapping
from dataclasses import dataclass
from typing import Any

import torch

from .gaussians import quat_to_rotmat
from .rasterize import drawn

SPLIT_SCALE_DIVISOR = 1.6
REQUIRED = ("means", "quats", "scales", "opacities")

Params = MutableMapping[str, torch.nn.Parameter]  # a dict or a torch.nn.ParameterDict
Optimizers = Mapping[str, torch.optim.Optimizer]


@dataclass(frozen=True)
class DensifyStrategy:
    """Clone, split, prune and opacity reset, with 3D Gaussian splatting's defaults; the settings
    carry gsplat's names. max_gaussians caps growth: the steepest candidates win."""

    prune_opa: float = 0.005
    grow_grad2d: float = 0.0002
    grow_scale3d: float = 0.01
    prune_scale3d: float = 0.1
    refine_start_iter: int = 500
    refine_stop_iter: int = 15_000
    refine_every: int = 100
    reset_every: int = 3000
    max_gaussians: int = 2_000_000

    def check_sanity(self, params: Params, optimizers: Optimizers) -> None:
        """ValueError unless every trainable parameter has its own optimizer of one parameter and
        the parameters this strategy reads are there."""
        trainable = {name for name, p in params.items() if p.requires_grad}
        if trainable != set(optimizers):
            raise ValueError(f"trainable parameters {sorted(trainable)} and optimizers {sorted(optimizers)} differ")
        for name, optimizer in optimizers.items():
            groups = optimizer.param_groups
            if len(groups) != 1 or len(groups[0]["params"]) != 1 or groups[0]["params"][0] is not params[name]:
                raise ValueError(f"the optimizer of {name!r} must hold that parameter alone")
        missing = [name for name in REQUIRED if name not in params]
        if missing:
            raise ValueError(f"densification needs the parameters {', '.join(missing)}")

    def initialize_state(self, scene_scale: float = 1.0) -> dict[str, Any]:
        """All the strategy remembers between steps: per Gaussian the sum of its gradient norms
        (grad2d) and of the views that drew it (count), made at the first step on the gradients'
        device, and the scene scale of the size thresholds."""
        return {"grad2d": None, "count": None, "scene_scale": scene_scale}

    def step_pre_backward(self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int,
                          info: dict[str, Any]) -> None:
        """Ask autograd to keep the gradient of the projected centres."""
        if info["means2d"].requires_grad:
            info["means2d"].retain_grad()

    def step_post_backward(self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int,
                           info: dict[str, Any], packed: bool = False) -> dict[str, int]:
        """After the optimizers stepped: accumulate the statistics, refine and reset when due.
        Returns counts of what was done (gsplat's strategies return nothing)."""
        done = {"cloned": 0, "split": 0, "pruned": 0, "reset": 0}
        if step >= self.refine_stop_iter:
            return done
        accumulate(state, info, len(params["means"]), packed)
        if step > self.refine_start_iter and step % self.refine_every == 0:
            done.update(self.refine(params, optimizers, state, step))
        if step > 0 and step % self.reset_every == 0:
            reset_opacity(params, optimizers, state, 2 * self.prune_opa)
            done["reset"] = 1
        return done

    def refine(self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int) -> dict[str, int]:
        """One growth-and-prune round from the accumulated gradients, which it then sets to zero."""
        grad = state["grad2d"] / state["count"].clamp_min(1)
        high = grad > self.grow_grad2d
        limit = state["scene_scale"]
        small = params["scales"].detach().exp().amax(-1) <= self.grow_scale3d * limit
        room = max(self.max_gaussians - len(grad), 0)
        if int(high.sum()) > room:  # each clone or split adds one Gaussian: keep the steepest
            steepest = torch.topk(torch.where(high, grad, -1.0), room).indices
            high = torch.zeros_like(high)
            high[steepest] = True
        to_clone = high & small
        to_split = high & ~small
        n_clone, n_split = int(to_clone.sum()), int(to_split.sum())
        clone(params, optimizers, state, to_clone)
        # Clones were appended at the end, never split in the same round.
        split(params, optimizers, state, torch.cat([to_split, to_split.new_zeros(n_clone)]))
        to_prune = torch.sigmoid(params["opacities"].detach()) < self.prune_opa
        if step > self.reset_every:
            to_prune = to_prune | (params["scales"].detach().exp().amax(-1) > self.prune_scale3d * limit)
        n_prune = int(to_prune.sum())
        prune(params, optimizers, state, to_prune)
        state["grad2d"].zero_()
        state["count"].zero_()
        return {"cloned": n_clone, "split": n_split, "pruned": n_prune}


def accumulate(state: dict[str, Any], info: dict[str, Any], n: int, packed: bool = False) -> None:
    """Add one step's gradient norms of the projected centres (NDC units) and the views that drew
    each Gaussian to state["grad2d"] and state["count"]. Unpacked info has means2d (C,N,2) and
    radii (C,N,2); packed info (gsplat's packed=True) has them per drawn pair, with gaussian_ids."""
    means2d = info["means2d"]
    if state["grad2d"] is None:
        state["grad2d"] = torch.zeros(n, device=means2d.device)
        state["count"] = torch.zeros(n, device=means2d.device)
    grad = means2d.grad
    if grad is None:
        return
    scale = torch.tensor([info["width"] / 2, info["height"] / 2], device=grad.device) * info["n_cameras"]
    norms = (grad.detach() * scale).norm(dim=-1)
    if packed:
        ids = info["gaussian_ids"]
        state["grad2d"].index_add_(0, ids, norms.to(state["grad2d"].dtype))
        state["count"].index_add_(0, ids, torch.ones_like(norms, dtype=state["count"].dtype))
        return
    visible = drawn(info["radii"])
    state["grad2d"] += torch.where(visible, norms, 0).sum(0).to(state["grad2d"].dtype)
    state["count"] += visible.sum(0).to(state["count"].dtype)


# --- the operations ------------------------------------------------------------------------------

def clone(params: Params, optimizers: Optimizers, state: dict[str, Any], mask: torch.Tensor) -> None:
    """Append an exact copy of every Gaussian in `mask`; the copies start with zero moments."""
    if not bool(mask.any()):
        return
    _edit_rows(state, len(mask), lambda v: torch.cat([v, v[mask]]))
    _edit(params, optimizers, lambda name, p: torch.cat([p, p[mask]]),
          lambda s: torch.cat([s, torch.zeros_like(s[mask])]))


def split(params: Params, optimizers: Optimizers, state: dict[str, Any], mask: torch.Tensor,
          generator: torch.Generator | None = None) -> None:
    """Replace every Gaussian in `mask` by two samples of itself with scales / 1.6."""
    k = int(mask.sum())
    if k == 0:
        return
    scales = params["scales"].detach()[mask].exp()
    R = quat_to_rotmat(params["quats"].detach()[mask])
    noise = torch.randn(2, k, 3, generator=generator, dtype=scales.dtype).to(scales.device)
    offsets = torch.einsum("kij,bkj->bki", R, noise * scales).reshape(2 * k, 3)

    def twice(v: torch.Tensor) -> torch.Tensor:
        return v.repeat(2, *([1] * (v.dim() - 1)))

    def child(name: str, p: torch.Tensor) -> torch.Tensor:
        parents = twice(p[mask])
        if name == "means":
            parents = parents + offsets.to(p.dtype)
        elif name == "scales":
            parents = parents - math.log(SPLIT_SCALE_DIVISOR)
        return torch.cat([p[~mask], parents])

    _edit_rows(state, len(mask), lambda v: torch.cat([v[~mask], twice(v[mask])]))
    _edit(params, optimizers, child, lambda s: torch.cat([s[~mask], twice(torch.zeros_like(s[mask]))]))


def prune(params: Params, optimizers: Optimizers, state: dict[str, Any], mask: torch.Tensor) -> None:
    """Remove every Gaussian in `mask`."""
    if bool(mask.any()):
        _edit_rows(state, len(mask), lambda v: v[~mask])
        _edit(params, optimizers, lambda name, p: p[~mask], lambda s: s[~mask])


def reset_opacity(params: Params, optimizers: Optimizers, state: dict[str, Any], value: float) -> None:
    """Lower every opacity to at most `value` and forget the opacities' Adam moments."""
    logit = math.log(value / (1 - value))
    _edit(params, optimizers, lambda name, p: p.clamp_max(logit), torch.zeros_like, names=("opacities",))


def prune_outside_masks(params: Params, optimizers: Optimizers, state: dict[str, Any], viewmats: torch.Tensor,
                        Ks: torch.Tensor, masks: torch.Tensor, min_views: int = 1) -> int:
    """Remove Gaussians whose centre falls on the background of at least `min_views` masks.

    masks (V,H,W) bool, True on the object; a view counts only where the centre is in front of
    the camera and inside the image (pixel centres at integer coordinates). Returns how many
    Gaussians were removed.
    """
    outside = outside_mask_votes(params["means"].detach(), viewmats, Ks, masks) >= min_views
    prune(params, optimizers, state, outside)
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


def _edit_rows(state: dict[str, Any], n: int, fn: Callable[[torch.Tensor], torch.Tensor]) -> None:
    """Apply fn to the per-Gaussian rows of the state: its tensors of n rows (gsplat's ops edit every
    tensor of the state; a strategy may also keep tables there, such as MCMCStrategy's binomials)."""
    for key, value in state.items():
        if torch.is_tensor(value) and value.dim() > 0 and value.shape[0] == n:
            state[key] = fn(value)


def _edit(params: Params, optimizers: Optimizers, param_fn: Callable[[str, torch.Tensor], torch.Tensor],
          moment_fn: Callable[[torch.Tensor], torch.Tensor], names: tuple[str, ...] | None = None) -> None:
    """Replace parameters by param_fn(name, old) and their per-row optimizer moments by moment_fn."""
    for name in names or list(params.keys()):
        old = params[name]
        new = torch.nn.Parameter(param_fn(name, old.detach()), requires_grad=old.requires_grad)
        params[name] = new
        optimizer = optimizers.get(name)
        if optimizer is None:
            continue
        for group in optimizer.param_groups:
            group["params"] = [new if p is old else p for p in group["params"]]
        moments = optimizer.state.pop(old, None)
        if moments:
            optimizer.state[new] = {k: moment_fn(v) if torch.is_tensor(v) and v.shape == old.shape else v
                                    for k, v in moments.items()}
