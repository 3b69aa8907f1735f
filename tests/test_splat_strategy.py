"""Densification: the operations, DensifyStrategy with its explicit state, and the trainers driven
by strategies written to gsplat's API (one written here, and gsplat's own when it is installed)."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Any

import pytest
import torch
from gsplat.strategy import DefaultStrategy

from manus_capture.splat.gaussians import Gaussians, covariance
from manus_capture.splat.hand import HandConfig, HandGaussians, random_poses, train_hand
from manus_capture.splat.optimize import LearningRates, make_optimizers
from manus_capture.splat.reference import render_reference
from manus_capture.splat.strategy import (
    DensifyStrategy,
    accumulate,
    clone,
    prune,
    prune_outside_masks,
    reset_opacity,
    split,
)
from manus_capture.splat.trainer import ObjectConfig, Views, train_object
from manus_core.progress import silent


def make_gaussians(n: int = 6, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    sh = torch.randn(n, 4, 3, generator=g)
    return Gaussians(torch.randn(n, 3, generator=g), torch.randn(n, 4, generator=g),
                     torch.log(torch.rand(n, 3, generator=g) * 0.05 + 0.01), torch.randn(n, generator=g), sh, 1)


def stepped_optimizers(gaussians: Gaussians) -> dict[str, torch.optim.Adam]:
    """An Adam per parameter with non-zero moments."""
    optimizers = make_optimizers(gaussians, LearningRates(), 1.0)
    loss = sum((p ** 2).sum() for p in gaussians.parameters())
    loss.backward()
    for opt in optimizers.values():
        opt.step()
        opt.zero_grad()
    return optimizers


def moments(optimizers: dict, gaussians: Gaussians, name: str) -> torch.Tensor:
    return optimizers[name].state[gaussians.params[name]]["exp_avg"]


def test_clone_appends_exact_copies_with_fresh_moments():
    g = make_gaussians()
    opt = stepped_optimizers(g)
    before = g.tensors()
    old_moments = moments(opt, g, "means").clone()
    state = {"grad2d": torch.arange(6.0), "scene_scale": 1.0}
    mask = torch.tensor([True, False, True, False, False, False])
    clone(g.params, opt, state, mask)
    assert len(g) == 8
    for name, value in before.items():
        assert torch.equal(g.params[name][:6], value)
        assert torch.equal(g.params[name][6:], value[mask])
    assert torch.equal(moments(opt, g, "means")[:6], old_moments)
    assert float(moments(opt, g, "means")[6:].abs().max()) == 0.0
    assert torch.equal(state["grad2d"], torch.tensor([0.0, 1, 2, 3, 4, 5, 0, 2]))  # the state's rows follow
    # The optimizer now steps the new tensors.
    assert opt["means"].param_groups[0]["params"][0] is g.params["means"]
    g.params["means"].sum().backward()
    opt["means"].step()


def test_split_draws_children_from_the_parent_distribution():
    k = 4000
    quat = torch.tensor([[0.9, 0.2, -0.3, 0.1]])
    log_s = torch.log(torch.tensor([[0.05, 0.02, 0.01]]))
    g = Gaussians(torch.tensor([[1.0, 2.0, 3.0]]).repeat(k, 1), quat.repeat(k, 1), log_s.repeat(k, 1),
                  torch.zeros(k), torch.zeros(k, 1, 3), 0)
    g.params["means"].data[0, 0] += 10  # one Gaussian that is not split
    opt = stepped_optimizers(g)
    before = g.tensors()
    mask = torch.ones(k, dtype=torch.bool)
    mask[0] = False
    state = {"count": torch.arange(float(k))}
    split(g.params, opt, state, mask, generator=torch.Generator().manual_seed(0))
    assert len(g) == 1 + 2 * (k - 1)
    assert torch.equal(state["count"], torch.cat([torch.zeros(1), torch.arange(1.0, k).repeat(2)]))
    assert torch.equal(g.means[0], before["means"][0])  # the unsplit one comes first, unchanged
    parent_mean, parent_log_s, parent_quat = before["means"][1], before["scales"][1], before["quats"][1]
    assert torch.allclose(g.params["scales"][1:], parent_log_s - math.log(1.6), atol=1e-6)
    assert torch.equal(g.params["quats"][1:], parent_quat.expand(2 * (k - 1), 4))
    # The children's spread is the parent's covariance (sampling error ~ 1/sqrt(8000)).
    children = g.means[1:].detach()
    parent_cov = covariance(parent_quat, torch.exp(parent_log_s))
    emp = torch.cov(children.T)
    assert torch.allclose(emp, parent_cov, atol=0.05 * float(parent_cov.diagonal().max()))
    assert torch.allclose(children.mean(0), parent_mean, atol=3e-3)
    assert float(moments(opt, g, "means")[1:].abs().max()) == 0.0


def test_prune_and_opacity_reset():
    g = make_gaussians()
    opt = stepped_optimizers(g)
    keep = g.tensors()["means"][[0, 2, 3, 5]]
    state = {"grad2d": torch.arange(6.0), "binoms": torch.ones(3, 3)}
    prune(g.params, opt, state, torch.tensor([False, True, False, False, True, False]))
    assert torch.equal(g.means.detach(), keep)
    assert moments(opt, g, "means").shape == (4, 3)
    # per-Gaussian rows are pruned, a table of another size (MCMCStrategy's binomials) is kept
    assert torch.equal(state["grad2d"], torch.tensor([0.0, 2, 3, 5])) and state["binoms"].shape == (3, 3)

    g.params["opacities"].data = torch.tensor([-8.0, -1.0, 0.0, 3.0])
    reset_opacity(g.params, opt, state, 0.01)
    assert torch.allclose(g.opacities.detach(), torch.tensor([torch.sigmoid(torch.tensor(-8.0)).item(),
                                                             0.01, 0.01, 0.01]), atol=1e-7)
    assert float(moments(opt, g, "opacities").abs().max()) == 0.0
    assert float(moments(opt, g, "means").abs().max()) > 0  # other moments are kept


def refine_info(gradients: list[float], n_cameras: int = 1) -> dict[str, Any]:
    """The rasterizer's info for one camera of 100x100 pixels seeing every Gaussian, with the pixel
    gradients of the centres set (x 50, half the width, gives NDC units)."""
    n = len(gradients)
    means2d = torch.zeros(n_cameras, n, 2, requires_grad=True)
    (means2d * torch.tensor(gradients)[None, :, None]).sum().backward()
    return {"means2d": means2d, "radii": torch.ones(n_cameras, n, 2, dtype=torch.long), "width": 100, "height": 100,
            "n_cameras": n_cameras, "gaussian_ids": None}


def test_refine_from_gradients_with_an_explicit_state():
    """High-gradient small Gaussians are cloned, large ones split, transparent ones pruned; all the
    strategy learns lives in the state dict."""
    n = 6
    g = Gaussians(torch.zeros(n, 3), torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                  torch.log(torch.tensor([0.005, 0.005, 0.05, 0.05, 0.005, 0.005]))[:, None].repeat(1, 3),
                  torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, -10.0]), torch.zeros(n, 1, 3), 0)
    opt = stepped_optimizers(g)
    scales = g.scales.detach()[:, 0].clone()
    s = DensifyStrategy(grow_grad2d=0.001, grow_scale3d=0.01, refine_start_iter=0, refine_every=10, reset_every=1000)
    s.check_sanity(g.params, opt)
    state = s.initialize_state(scene_scale=1.0)
    assert state == {"grad2d": None, "count": None, "scene_scale": 1.0}
    info = refine_info([2e-5, 0.0, 2e-5, 0.0, 0.0, 0.0])
    s.step_pre_backward(g.params, opt, state, 5, info)
    done = s.step_post_backward(g.params, opt, state, 5, info, packed=False)  # not a refine step: statistics only
    assert done == {"cloned": 0, "split": 0, "pruned": 0, "reset": 0}
    assert torch.equal(state["count"], torch.ones(n))
    assert torch.allclose(state["grad2d"], torch.tensor([1e-3 * math.sqrt(2), 0, 1e-3 * math.sqrt(2), 0, 0, 0]))
    done = s.step_post_backward(g.params, opt, state, 10, info)
    # grad 2e-5 * 50 * sqrt(2) = 1.4e-3 > 1e-3 for Gaussians 0 (small: clone) and 2 (large: split).
    assert done == {"cloned": 1, "split": 1, "pruned": 1, "reset": 0}
    assert len(g) == 6 + 1 + 1 - 1
    # Order: survivors 0, 1, 3, 4 (2 was split, 5 pruned), the clone of 0, then the two children.
    expected = torch.cat([scales[[0, 1, 3, 4]], scales[[0]], scales[[2, 2]] / 1.6])
    assert torch.allclose(g.scales.detach()[:, 0], expected, rtol=1e-6)
    # The statistics start again from zero, one row per Gaussian.
    assert torch.equal(state["grad2d"], torch.zeros(7)) and torch.equal(state["count"], torch.zeros(7))


def test_packed_statistics_match_unpacked():
    """gsplat's packed info lists the drawn (camera, Gaussian) pairs; the sums are the same."""
    info = refine_info([1e-5, 2e-5, 3e-5], n_cameras=2)
    info["radii"][1, 1] = 0  # camera 1 does not draw Gaussian 1
    unpacked = {"grad2d": None, "count": None}
    accumulate(unpacked, info, 3)
    visible = info["radii"].all(-1)
    packed_info = {**info, "means2d": info["means2d"].detach()[visible].requires_grad_(),
                   "gaussian_ids": torch.nonzero(visible)[:, 1]}
    packed_info["means2d"].grad = info["means2d"].grad[visible]
    packed = {"grad2d": None, "count": None}
    accumulate(packed, packed_info, 3, packed=True)
    assert torch.equal(packed["count"], torch.tensor([2.0, 1.0, 2.0])) and torch.equal(packed["count"], unpacked["count"])
    assert torch.allclose(packed["grad2d"], unpacked["grad2d"])


def test_check_sanity_wants_one_optimizer_per_parameter():
    g = make_gaussians()
    opt = stepped_optimizers(g)
    DensifyStrategy().check_sanity(g.params, opt)
    with pytest.raises(ValueError, match="optimizers"):
        DensifyStrategy().check_sanity(g.params, {k: v for k, v in opt.items() if k != "sh0"})
    with pytest.raises(ValueError, match="'means'"):
        DensifyStrategy().check_sanity(g.params, {**opt, "means": opt["quats"]})


def test_prune_outside_masks():
    # A camera at the origin looking down +z; the mask keeps the left half of the image.
    K = torch.tensor([[[10.0, 0, 9.5], [0, 10.0, 9.5], [0, 0, 1]]])
    V = torch.eye(4)[None]
    masks = torch.zeros(1, 20, 20, dtype=torch.bool)
    masks[:, :, :10] = True
    means = torch.tensor([[-0.5, 0, 2], [0.5, 0, 2], [-0.1, 0.3, 1], [0.0, 0.0, -1.0], [30.0, 0, 1]])
    n = len(means)
    g = Gaussians(means, torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.zeros(n, 3), torch.zeros(n),
                  torch.zeros(n, 1, 3), 0)
    removed = prune_outside_masks(g.params, {}, {}, V, K, masks)
    # Removed: the right-half point. Kept: left-half points, one behind the camera and one
    # outside the image (no view says it is background).
    assert removed == 1
    assert torch.equal(g.means.detach(), means[[0, 2, 3, 4]])
    assert prune_outside_masks(g.params, {}, {}, V, K, masks, min_views=2) == 0


@pytest.mark.parametrize("room", [0, 1])
def test_growth_respects_the_cap(room):
    g = make_gaussians(4)
    opt = stepped_optimizers(g)
    s = DensifyStrategy(grow_grad2d=0.0, prune_opa=0.0, max_gaussians=4 + room, refine_start_iter=0, refine_every=1)
    means2d = torch.zeros(1, 4, 2, requires_grad=True)
    (means2d * torch.arange(1.0, 5.0)[None, :, None]).sum().backward()
    info = {"means2d": means2d, "radii": torch.ones(1, 4, 2), "width": 10, "height": 10, "n_cameras": 1,
            "gaussian_ids": None}
    s.step_post_backward(g.params, opt, s.initialize_state(), 1, info)
    assert len(g) == 4 + room
    assert math.isfinite(float(g.means.detach().sum()))


# --- the trainers driven by strategies with gsplat's API ---------------------------------------------

def _update_param_with_optimizer(param_fn, optimizer_fn, params, optimizers) -> None:
    """What gsplat.strategy.ops does to a parameter and its optimizer (written out, gsplat aside)."""
    for name in list(params.keys()):
        param = params[name]
        new_param = torch.nn.Parameter(param_fn(param), requires_grad=param.requires_grad)
        params[name] = new_param
        optimizer = optimizers[name]
        for i in range(len(optimizer.param_groups)):
            param_state = optimizer.state[param]
            del optimizer.state[param]
            for key in param_state.keys():
                if key != "step":
                    param_state[key] = optimizer_fn(param_state[key])
            optimizer.param_groups[i]["params"] = [new_param]
            optimizer.state[new_param] = param_state


@dataclass
class TopKStrategy:
    """A strategy in the shape of gsplat's: every `refine_every` steps it duplicates the `grow`
    Gaussians of largest mean screen gradient and removes the `shrink` most transparent ones. Its
    statistics live in the state dict; `log` records, after each step, (step, Gaussians, rows of
    the state) for the test."""

    refine_start_iter: int = 0
    refine_stop_iter: int = 1000
    refine_every: int = 5
    grow: int = 6
    shrink: int = 2
    log: list = field(default_factory=list)

    def check_sanity(self, params, optimizers) -> None:
        assert {n for n, p in params.items() if p.requires_grad} == set(optimizers)
        for key in ["means", "scales", "quats", "opacities"]:
            assert key in params
        assert all(len(optimizer.param_groups) == 1 for optimizer in optimizers.values())

    def initialize_state(self, scene_scale: float = 1.0) -> dict[str, Any]:
        return {"grad2d": None, "count": None, "scene_scale": scene_scale}

    def step_pre_backward(self, params, optimizers, state, step, info) -> None:
        info["means2d"].retain_grad()

    def step_post_backward(self, params, optimizers, state, step, info, packed=False) -> None:
        for key in ["width", "height", "n_cameras", "radii", "gaussian_ids", "means2d"]:
            assert key in info
        n = len(params["means"])
        if state["grad2d"] is None:
            state["grad2d"], state["count"] = torch.zeros(n), torch.zeros(n)
        assert len(state["grad2d"]) == n  # the trainer's mask pruning kept the state's rows in step
        grads = info["means2d"].grad.clone()
        grads[..., 0] *= info["width"] / 2.0 * info["n_cameras"]
        grads[..., 1] *= info["height"] / 2.0 * info["n_cameras"]
        sel = (info["radii"] > 0).all(dim=-1)
        ids = torch.where(sel)[1]
        state["grad2d"].index_add_(0, ids, grads[sel].norm(dim=-1))
        state["count"].index_add_(0, ids, torch.ones_like(ids, dtype=torch.float32))
        if self.refine_start_iter < step < self.refine_stop_iter and step % self.refine_every == 0:
            best = torch.topk(state["grad2d"] / state["count"].clamp_min(1), self.grow).indices
            _update_param_with_optimizer(lambda p: torch.cat([p, p[best]]),
                                         lambda v: torch.cat([v, torch.zeros_like(v[best])]), params, optimizers)
            state["grad2d"], state["count"] = torch.zeros(n + self.grow), torch.zeros(n + self.grow)
            faint = torch.topk(-params["opacities"].detach(), self.shrink).indices
            keep = torch.ones(n + self.grow, dtype=torch.bool)
            keep[faint] = False
            _update_param_with_optimizer(lambda p: p[keep], lambda v: v[keep], params, optimizers)
            state["grad2d"], state["count"] = state["grad2d"][keep], state["count"][keep]
        self.log.append((step, len(params["means"]), len(state["grad2d"])))


@pytest.fixture(scope="module")
def ring() -> Views:
    """12 Gaussians seen by 8 cameras of 24x24 pixels on a ring, with object masks."""
    g = torch.Generator().manual_seed(1)
    n = 12
    truth = ((torch.rand(n, 3, generator=g) - 0.5) * 0.5, torch.randn(n, 4, generator=g),
             torch.rand(n, 3, generator=g) * 0.06 + 0.04, torch.rand(n, generator=g) * 0.5 + 0.5,
             torch.rand(n, 3, generator=g))
    viewmats = []
    for i in range(8):
        az = 2 * math.pi * i / 8
        centre = torch.tensor([math.cos(az), math.sin(az), 0.3]) * 2.5
        z = -centre / centre.norm()
        x = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0]), z)
        x = x / x.norm()
        R = torch.stack([x, torch.linalg.cross(z, x), z])
        V = torch.eye(4)
        V[:3, :3], V[:3, 3] = R, -R @ centre
        viewmats.append(V)
    Ks = torch.tensor([[26.0, 0, 11.5], [0, 26.0, 11.5], [0, 0, 1]]).repeat(8, 1, 1)
    images, alpha = render_reference(*truth, torch.stack(viewmats), Ks, 24, 24, background=torch.zeros(3))
    return Views(images.float(), Ks, torch.stack(viewmats), alpha[..., 0] > 0.01)


def _train(views: Views, strategy, iterations: int = 24, progress=silent):
    cfg = ObjectConfig(iterations=iterations, sh_degree=0, init_points=80, densify=strategy,
                       lr=LearningRates(means=1.6e-3, means_final=1.6e-5))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # LPIPS is off without weights
        return train_object(views, cfg, progress=progress)


def test_the_object_trainer_runs_a_strategy_written_to_gsplats_api(ring):
    strategy = TopKStrategy()
    calls = []
    result = _train(ring, strategy, progress=lambda *call: calls.append(call))
    assert calls == [("object", step, 24) for step in range(25)]
    n = [r["n"] for r in result.history]
    assert [step for step, *_ in strategy.log] == list(range(1, 25))
    for (step, count, rows), record in zip(strategy.log, result.history):
        assert rows == count  # the state's rows follow every edit of the Gaussians
        if step % 5 == 0:
            assert count == record["n"] + 6 - 2
        else:
            assert count == record["n"]
    # the trainer's mask pruning runs on the strategy's refine steps, on the same state
    pruned = sum(r.get("mask_pruned", 0) for r in result.history)
    assert n[0] == 80 and len(result.gaussians) == 80 + 4 * 4 - pruned
    assert all(k not in r for r in result.history for k in ("cloned", "split"))  # gsplat's report nothing


def test_the_hand_trainer_runs_a_strategy_written_to_gsplats_api():
    """The skinning grid's optimizer steps too, but no strategy sees it."""
    model = HandGaussians.initialize(per_bone=4, sh_degree=0, resolution=16)
    grid = model.skin_grid.detach().clone()
    poses = random_poses(2, model.skeleton, torch.Generator().manual_seed(0), rotation=0.3, translation=0.0)
    K = torch.tensor([[60.0, 0, 15.5], [0, 60.0, 15.5], [0, 0, 1]])
    V = torch.eye(4)
    V[2, 3] = 0.5
    views = []
    for pose in poses:
        with torch.no_grad():
            rgb, alpha = model.render(pose, V[None], K[None], 32, 32, torch.zeros(3))
        views.append(Views(rgb.roll(1, dims=2), K[None], V[None], None))
    strategy = TopKStrategy(refine_every=4, grow=5, shrink=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # LPIPS is off without weights
        history = train_hand(model, poses, views, HandConfig(iterations=8, sh_degree=0, densify=strategy,
                                                             skin_lr=1e-3))
    assert [count for _, count, _ in strategy.log] == [80, 80, 80, 84, 84, 84, 84, 88]
    assert [r["n"] for r in history] == [80, 80, 80, 80, 84, 84, 84, 84] and len(model) == 88
    assert not torch.equal(model.skin_grid.detach(), grid)


class _Spy:
    """Wraps a strategy's step_post_backward to record (Gaussians, rows of state['grad2d'], its sum)."""

    def __init__(self, strategy) -> None:
        self.strategy, self.log = strategy, []

    def __getattr__(self, name):
        return getattr(self.strategy, name)

    def step_post_backward(self, params, optimizers, state, step, info, packed=False):
        done = self.strategy.step_post_backward(params, optimizers, state, step, info, packed=packed)
        self.log.append((len(params["means"]), len(state["grad2d"]), float(state["grad2d"].sum())))
        return done


def test_gsplats_default_strategy_drives_the_trainer(ring):
    torch.manual_seed(0)
    spy = _Spy(DefaultStrategy(refine_start_iter=4, refine_every=8, reset_every=1000,
                                               grow_grad2d=1e-6, grow_scale3d=1.0))
    result = _train(ring, spy)
    counts = [n for n, _, _ in spy.log]
    assert counts[7] > counts[6] and counts[15] > counts[14]  # steps 8 and 16 grew the model
    for n, rows, total in (spy.log[7], spy.log[15]):
        assert rows == n and total == 0.0  # after refining, the statistics start again from zero
    assert len(result.gaussians) == counts[-1]  # step 24 neither refines nor prunes outside the masks
