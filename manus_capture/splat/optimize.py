"""One training step of the object and hand trainers: Adam per parameter, the decay of the means'
step size, backward, and densification by any strategy with gsplat's API.

The optimizers are a dict name -> Adam of one parameter each, the form gsplat's strategies edit
(see strategy.py), so `DensifyStrategy` and gsplat's `DefaultStrategy` or `MCMCStrategy` all
drive the same loop through `Densification`.
"""

from __future__ import annotations

import inspect
import math
from dataclasses import dataclass
from typing import Any, Protocol

import torch

from .gaussians import PARAM_NAMES, Gaussians
from .strategy import Optimizers, Params


@dataclass
class LearningRates:
    """Adam step sizes per parameter (3DGS defaults); means scale with the scene and decay.
    `scales` and `opacities` are those of their logarithms and logits (the parameters)."""

    means: float = 1.6e-4
    means_final: float = 1.6e-6
    quats: float = 1e-3
    scales: float = 5e-3
    opacities: float = 5e-2
    sh0: float = 2.5e-3
    shN: float = 2.5e-3 / 20


def make_optimizers(gaussians: Gaussians, lr: LearningRates, scene_scale: float) -> dict[str, torch.optim.Adam]:
    """One Adam per Gaussian parameter (one named group each), keyed by PARAM_NAMES."""
    return {name: torch.optim.Adam([{"params": [gaussians.params[name]], "name": name,
                                     "lr": getattr(lr, name) * (scene_scale if name == "means" else 1.0)}], eps=1e-15)
            for name in PARAM_NAMES}


def decay_means_lr(optimizer: torch.optim.Optimizer, lr: LearningRates, scene_scale: float, step: int,
                   total: int) -> float:
    """Set the means' step size, decayed exponentially from lr.means to lr.means_final (times the
    scale) over `total` steps; returns it."""
    frac = min(step / max(total, 1), 1.0)
    value = scene_scale * math.exp((1 - frac) * math.log(lr.means) + frac * math.log(lr.means_final))
    for group in optimizer.param_groups:
        group["lr"] = value
    return value


class Strategy(Protocol):
    """gsplat's strategy API (gsplat.strategy.Strategy): DensifyStrategy, gsplat's DefaultStrategy and
    MCMCStrategy. MCMCStrategy's initialize_state takes no scene scale and its step_post_backward
    needs the means' step size `lr`; Densification passes what each asks for."""

    def check_sanity(self, params: Params, optimizers: Optimizers) -> None: ...

    def initialize_state(self, *args: Any, **kwargs: Any) -> dict[str, Any]: ...

    def step_pre_backward(self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int,
                          info: dict[str, Any]) -> None: ...

    def step_post_backward(self, params: Params, optimizers: Optimizers, state: dict[str, Any], step: int,
                           info: dict[str, Any], *args: Any, **kwargs: Any) -> Any: ...


@dataclass
class Densification:
    """A strategy at work on one model's parameters: the strategy holds its settings, `state`
    everything it learns between steps."""

    strategy: Strategy
    params: Params
    optimizers: Optimizers
    state: dict[str, Any]

    @classmethod
    def start(cls, strategy: Strategy, params: Params, optimizers: Optimizers, scene_scale: float) -> Densification:
        strategy.check_sanity(params, optimizers)
        if "scene_scale" in inspect.signature(strategy.initialize_state).parameters:
            return cls(strategy, params, optimizers, strategy.initialize_state(scene_scale=scene_scale))
        return cls(strategy, params, optimizers, strategy.initialize_state())

    def before_backward(self, step: int, info: dict[str, Any]) -> None:
        self.strategy.step_pre_backward(self.params, self.optimizers, self.state, step, info)

    def after_step(self, step: int, info: dict[str, Any], means_lr: float) -> dict[str, int]:
        """step_post_backward (after the optimizers stepped, as gsplat's trainer calls it); returns
        the counts a strategy reports (DensifyStrategy's cloned, split, pruned, reset), else {}."""
        accepted = inspect.signature(self.strategy.step_post_backward).parameters
        extra = {k: v for k, v in (("packed", False), ("lr", means_lr)) if k in accepted}
        return self.strategy.step_post_backward(self.params, self.optimizers, self.state, step, info, **extra) or {}

    def refines_at(self, step: int) -> bool:
        """Whether the strategy grows and prunes at `step`, read from gsplat's settings
        refine_start_iter, refine_stop_iter and refine_every (False for a strategy without them)."""
        try:
            start, stop, every = (self.strategy.refine_start_iter, self.strategy.refine_stop_iter,
                                  self.strategy.refine_every)
        except AttributeError:
            return False
        return start < step < stop and step % every == 0


def optimize_step(params: Params, optimizers: Optimizers, densify: Densification | None, loss: torch.Tensor,
                  parts: dict[str, float], info: dict[str, Any], step: int, means_lr: float) -> dict[str, float]:
    """Backward, a step of every optimizer and densification of one training step; returns the
    step's record (the Gaussians' count `n` is the one the step was rendered with)."""
    if densify is not None:
        densify.before_backward(step, info)
    loss.backward()
    for optimizer in optimizers.values():
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
    record = {"step": step, "loss": float(loss.detach()), "n": len(params["means"]), **parts}
    if densify is not None:
        record.update(densify.after_step(step, info, means_lr))
    return record
