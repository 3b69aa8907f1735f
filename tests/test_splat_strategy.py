"""Densification and pruning: clone, split, prune, opacity reset and mask pruning."""

from __future__ import annotations

import math

import pytest
import torch

from manus_capture.splat.gaussians import Gaussians, covariance
from manus_capture.splat.strategy import DensifyStrategy
from manus_capture.splat.trainer import LearningRates, make_optimizer


def make_gaussians(n: int = 6, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    sh = torch.randn(n, 4, 3, generator=g)
    return Gaussians(torch.randn(n, 3, generator=g), torch.randn(n, 4, generator=g),
                     torch.log(torch.rand(n, 3, generator=g) * 0.05 + 0.01), torch.randn(n, generator=g), sh, 1)


def stepped_optimizer(gaussians: Gaussians) -> torch.optim.Adam:
    """An Adam optimizer with non-zero moments for every parameter."""
    opt = make_optimizer(gaussians, LearningRates(), 1.0)
    loss = sum((p ** 2).sum() for p in gaussians.parameters())
    loss.backward()
    opt.step()
    opt.zero_grad()
    return opt


def moments(opt: torch.optim.Adam, gaussians: Gaussians, name: str) -> torch.Tensor:
    return opt.state[gaussians.params[name]]["exp_avg"]


def test_clone_appends_exact_copies_with_fresh_moments():
    g = make_gaussians()
    opt = stepped_optimizer(g)
    before = g.tensors()
    old_moments = moments(opt, g, "means").clone()
    mask = torch.tensor([True, False, True, False, False, False])
    DensifyStrategy().clone(g, opt, mask)
    assert len(g) == 8
    for name, value in before.items():
        assert torch.equal(g.params[name][:6], value)
        assert torch.equal(g.params[name][6:], value[mask])
    assert torch.equal(moments(opt, g, "means")[:6], old_moments)
    assert float(moments(opt, g, "means")[6:].abs().max()) == 0.0
    # The optimizer now steps the new tensors.
    assert opt.param_groups[0]["params"][0] is g.params["means"]
    g.params["means"].sum().backward()
    opt.step()


def test_split_draws_children_from_the_parent_distribution():
    k = 4000
    quat = torch.tensor([[0.9, 0.2, -0.3, 0.1]])
    log_s = torch.log(torch.tensor([[0.05, 0.02, 0.01]]))
    g = Gaussians(torch.tensor([[1.0, 2.0, 3.0]]).repeat(k, 1), quat.repeat(k, 1), log_s.repeat(k, 1),
                  torch.zeros(k), torch.zeros(k, 1, 3), 0)
    g.params["means"].data[0, 0] += 10  # one Gaussian that is not split
    opt = stepped_optimizer(g)
    before = g.tensors()
    mask = torch.ones(k, dtype=torch.bool)
    mask[0] = False
    DensifyStrategy().split(g, opt, mask, generator=torch.Generator().manual_seed(0))
    assert len(g) == 1 + 2 * (k - 1)
    assert torch.equal(g.means[0], before["means"][0])  # the unsplit one comes first, unchanged
    parent_mean, parent_log_s, parent_quat = before["means"][1], before["log_scales"][1], before["quats"][1]
    assert torch.allclose(g.params["log_scales"][1:], parent_log_s - math.log(1.6), atol=1e-6)
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
    opt = stepped_optimizer(g)
    s = DensifyStrategy(prune_opacity=0.005)
    keep = g.tensors()["means"][[0, 2, 3, 5]]
    s.prune(g, opt, torch.tensor([False, True, False, False, True, False]))
    assert torch.equal(g.means.detach(), keep)
    assert moments(opt, g, "means").shape == (4, 3)

    g.params["opacity_logits"].data = torch.tensor([-8.0, -1.0, 0.0, 3.0])
    s.reset_opacity(g, opt)
    assert torch.allclose(g.opacities.detach(), torch.tensor([torch.sigmoid(torch.tensor(-8.0)).item(),
                                                             0.01, 0.01, 0.01]), atol=1e-7)
    assert float(moments(opt, g, "opacity_logits").abs().max()) == 0.0
    assert float(moments(opt, g, "means").abs().max()) > 0  # other moments are kept


def test_refine_from_gradients():
    """High-gradient small Gaussians are cloned, large ones split, transparent ones pruned."""
    n = 6
    g = Gaussians(torch.zeros(n, 3), torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                  torch.log(torch.tensor([0.005, 0.005, 0.05, 0.05, 0.005, 0.005]))[:, None].repeat(1, 3),
                  torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, -10.0]), torch.zeros(n, 1, 3), 0)
    opt = stepped_optimizer(g)
    scales = g.scales.detach()[:, 0].clone()
    s = DensifyStrategy(scene_scale=1.0, grow_grad2d=0.001, grow_scale3d=0.01, refine_start=0,
                        refine_every=10, reset_every=1000)
    means2d = torch.zeros(1, n, 2, requires_grad=True)
    # Pixel gradients in a 100x100 image: x 50 (half the width) gives NDC units.
    (means2d * torch.tensor([[[2e-5], [0.0], [2e-5], [0.0], [0.0], [0.0]]])).sum().backward()
    meta = {"means2d": means2d, "visible": torch.ones(1, n, dtype=torch.bool), "width": 100, "height": 100,
            "n_cameras": 1}
    done = s.after_backward(g, opt, meta, step=5)  # not a refine step: statistics only
    assert done == {"cloned": 0, "split": 0, "pruned": 0, "reset": 0}
    done = s.after_backward(g, opt, meta, step=10)
    # grad 2e-5 * 50 * sqrt(2) = 1.4e-3 > 1e-3 for Gaussians 0 (small: clone) and 2 (large: split).
    assert done == {"cloned": 1, "split": 1, "pruned": 1, "reset": 0}
    assert len(g) == 6 + 1 + 1 - 1
    # Order: survivors 0, 1, 3, 4 (2 was split, 5 pruned), the clone of 0, then the two children.
    expected = torch.cat([scales[[0, 1, 3, 4]], scales[[0]], scales[[2, 2]] / 1.6])
    assert torch.allclose(g.scales.detach()[:, 0], expected, rtol=1e-6)


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
    removed = DensifyStrategy().prune_outside_masks(g, None, V, K, masks)
    # Removed: the right-half point. Kept: left-half points, one behind the camera and one
    # outside the image (no view says it is background).
    assert removed == 1
    assert torch.equal(g.means.detach(), means[[0, 2, 3, 4]])
    assert DensifyStrategy().prune_outside_masks(g, None, V, K, masks, min_views=2) == 0


@pytest.mark.parametrize("room", [0, 1])
def test_growth_respects_the_cap(room):
    g = make_gaussians(4)
    opt = stepped_optimizer(g)
    s = DensifyStrategy(grow_grad2d=0.0, prune_opacity=0.0, max_gaussians=4 + room, refine_start=0, refine_every=1)
    means2d = torch.zeros(1, 4, 2, requires_grad=True)
    (means2d * torch.arange(1.0, 5.0)[None, :, None]).sum().backward()
    meta = {"means2d": means2d, "visible": torch.ones(1, 4, dtype=torch.bool), "width": 10, "height": 10,
            "n_cameras": 1}
    s.after_backward(g, opt, meta, step=1)
    assert len(g) == 4 + room
    assert math.isfinite(float(g.means.detach().sum()))
