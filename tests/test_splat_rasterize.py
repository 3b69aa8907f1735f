"""The tile rasterizer against the dense reference renderer, its gradients, and its conventions."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from manus_capture.splat import rasterize
from manus_capture.splat.gaussians import covariance, quat_to_rotmat
from manus_capture.splat.rasterize import project
from manus_capture.splat.reference import render_reference
from manus_capture.splat.sh import eval_sh, num_sh_bases
from manus_core.cameras import CameraRig


def random_scene(seed: int, n: int, cams: int, width: int, height: int, dtype=torch.float64):
    """n Gaussians around the origin seen by cameras ~2.5 m away with skewed, off-centre intrinsics."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * 0.3
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * 0.15 + 0.02
    opacities = torch.rand(n, generator=g, dtype=dtype) * 0.9 + 0.05
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    viewmats, Ks = [], []
    for _ in range(cams):
        axis_angle = torch.randn(3, generator=g, dtype=dtype) * 0.3
        R = quat_to_rotmat(torch.cat([torch.ones(1, dtype=dtype), 0.5 * axis_angle]))
        t = torch.tensor([0.1, -0.05, 2.5], dtype=dtype) + torch.randn(3, generator=g, dtype=dtype) * 0.1
        V = torch.eye(4, dtype=dtype)
        V[:3, :3], V[:3, 3] = R, t
        viewmats.append(V)
        f = width * (1.0 + 0.2 * float(torch.rand(1, generator=g)))
        Ks.append(torch.tensor([[f, 0.3, width / 2 - 0.3], [0, 0.95 * f, height / 2 + 0.7], [0, 0, 1]], dtype=dtype))
    return means, quats, scales, opacities, colors, torch.stack(viewmats), torch.stack(Ks)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rasterize_equals_dense_reference(seed):
    W, H = 37, 29
    scene = random_scene(seed, 30, 3, W, H)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    rgb, alpha = rasterize(*scene, W, H, background=bg, tile_size=8)
    ref_rgb, ref_alpha = render_reference(*scene, W, H, background=bg)
    assert rgb.shape == (3, H, W, 3) and alpha.shape == (3, H, W, 1)
    # The scenes are not trivial: splats overlap and cover much of the images.
    assert 0.1 < float(alpha.mean()) < 0.9
    assert float(alpha.max()) > 0.9
    assert torch.allclose(rgb, ref_rgb, atol=1e-5, rtol=0)
    assert torch.allclose(alpha, ref_alpha, atol=1e-5, rtol=0)


def test_precomputed_covariances_sh_and_tile_size_agree():
    W, H = 40, 24
    means, quats, scales, opac, colors, viewmats, Ks = random_scene(5, 25, 2, W, H)
    ref, _ = render_reference(means, quats, scales, opac, colors, viewmats, Ks, W, H)
    cov = covariance(quats, scales)
    for tile in (4, 16):
        rgb, _ = rasterize(means, None, None, opac, colors, viewmats, Ks, W, H, covars=cov, tile_size=tile)
        assert torch.allclose(rgb, ref, atol=1e-5, rtol=0)
    packed = cov[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]
    rgb, _ = rasterize(means, None, None, opac, colors, viewmats, Ks, W, H, covars=packed)
    assert torch.allclose(rgb, ref, atol=1e-5, rtol=0)

    # SH colours: the rasterizer's per-camera view directions match an explicit evaluation.
    sh = torch.randn(25, num_sh_bases(2), 3, dtype=torch.float64) * 0.3
    rgb, _ = rasterize(means, quats, scales, opac, sh, viewmats, Ks, W, H, sh_degree=2)
    for c in range(2):
        centre = -viewmats[c, :3, :3].T @ viewmats[c, :3, 3]
        per_cam = eval_sh(2, sh, means - centre)
        ref_c, _ = render_reference(means, quats, scales, opac, per_cam, viewmats[c:c + 1], Ks[c:c + 1], W, H)
        assert torch.allclose(rgb[c:c + 1], ref_c, atol=1e-5, rtol=0)


def test_float32_matches_float64_reference():
    W, H = 48, 40
    scene64 = random_scene(7, 60, 2, W, H)
    scene32 = [x.float() for x in scene64]
    rgb, _ = rasterize(*scene32, W, H, chunk_elements=1 << 14)  # many small chunks
    ref, _ = render_reference(*scene64, W, H)
    err = (rgb.double() - ref).abs()
    # A float32 rounding can flip a pixel across the alpha >= 1/255 cut-off; nearly all agree.
    assert float((err > 1e-5).double().mean()) < 1e-3
    assert float(err.median()) < 1e-6


def test_projection_matches_camera_rig():
    """Pixel centres at integer coordinates and x_cam = R x + t, as CameraRig.project."""
    W, H = 64, 48
    means, _, _, _, _, viewmats, Ks = random_scene(3, 10, 2, W, H)
    rig = CameraRig(("a", "b"), Ks.numpy(), np.zeros((2, 5)), viewmats[:, :3, :3].numpy(),
                    viewmats[:, :3, 3].numpy(), np.array([[W, H], [W, H]]))
    proj = project(means, torch.eye(3, dtype=torch.float64).expand(10, 3, 3) * 1e-4, viewmats, Ks, W, H)
    assert np.allclose(proj["means2d"].numpy(), rig.project(means.numpy()), atol=1e-9)


def test_pixel_centre_convention():
    """A small round splat centred on pixel (5, 7) peaks there and is symmetric about it."""
    W, H = 12, 14
    K = torch.tensor([[[100.0, 0, 5.0], [0, 100.0, 7.0], [0, 0, 1]]])
    V = torch.eye(4)[None]
    means = torch.tensor([[0.0, 0.0, 2.0]])
    scale = torch.full((1, 3), 0.03)  # 1.5 px
    rgb, alpha = rasterize(means, torch.tensor([[1.0, 0, 0, 0]]), scale, torch.tensor([0.9]),
                           torch.ones(1, 3), V, K, W, H)
    a = alpha[0, ..., 0]
    assert divmod(int(a.argmax()), W) == (7, 5)
    assert torch.allclose(a[7, 4], a[7, 6]) and torch.allclose(a[6, 5], a[8, 5])
    # With eps2d = 0.3 the screen variance is 1.5^2 + 0.3: one pixel off the centre the alpha
    # falls by exp(-1 / (2 * 2.55)).
    assert math.isclose(float(a[7, 6] / a[7, 5]), math.exp(-0.5 / 2.55), rel_tol=1e-4)


def test_culling_and_empty_views():
    W, H = 16, 16
    K = torch.tensor([[[20.0, 0, 8], [0, 20.0, 8], [0, 0, 1]]])
    V = torch.eye(4)[None]
    quats = torch.tensor([[1.0, 0, 0, 0]] * 2)
    scales = torch.full((2, 3), 0.05)
    # One Gaussian behind the camera, one far off to the side: nothing is drawn.
    means = torch.tensor([[0.0, 0.0, -1.0], [50.0, 0.0, 1.0]], requires_grad=True)
    bg = torch.tensor([0.1, 0.2, 0.3])
    rgb, alpha = rasterize(means, quats, scales, torch.ones(2) * 0.9, torch.ones(2, 3), V, K, W, H, background=bg)
    assert float(alpha.detach().abs().max()) == 0.0
    assert torch.allclose(rgb.detach(), bg.expand(1, H, W, 3))
    # A view with nothing in it still backpropagates (zeros), so training never trips on it.
    rgb.sum().backward()
    assert torch.equal(means.grad, torch.zeros(2, 3))


def test_batched_cameras_equal_single_renders():
    W, H = 30, 20
    means, quats, scales, opac, colors, viewmats, Ks = random_scene(11, 20, 3, W, H, torch.float32)
    batch, _ = rasterize(means, quats, scales, opac, colors, viewmats, Ks, W, H)
    for c in range(3):
        single, _ = rasterize(means, quats, scales, opac, colors, viewmats[c:c + 1], Ks[c:c + 1], W, H)
        assert torch.allclose(batch[c:c + 1], single, atol=1e-6)


def test_per_camera_centres_equal_one_render_per_camera():
    """means (C,N,3) and covariances (C,N,3,3), one scene per camera (a hand in one pose per view),
    render in one call what each camera's own call renders, colours by SH included; gradients reach
    every camera's centres."""
    W, H = 30, 20
    means, quats, scales, opac, colors, viewmats, Ks = random_scene(12, 20, 3, W, H, torch.float32)
    shift = torch.randn(3, 1, 3, generator=torch.Generator().manual_seed(1)) * 0.1
    per_cam = (means[None] + shift).requires_grad_(True)
    covars = covariance(quats, scales)[None].repeat(3, 1, 1, 1) * torch.tensor([1.0, 1.5, 0.7])[:, None, None, None]
    sh = torch.randn(20, 4, 3, generator=torch.Generator().manual_seed(2)) * 0.3
    batch, alpha = rasterize(per_cam, None, None, opac, sh, viewmats, Ks, W, H, covars=covars, sh_degree=1)
    for c in range(3):
        single, _ = rasterize(per_cam[c].detach(), None, None, opac, sh, viewmats[c:c + 1], Ks[c:c + 1], W, H,
                              covars=covars[c], sh_degree=1)
        assert torch.allclose(batch[c:c + 1], single, atol=1e-6)
    (batch.sum() + alpha.sum()).backward()
    assert (per_cam.grad.abs().sum((1, 2)) > 0).all()
    with pytest.raises(ValueError, match="per-camera means"):
        rasterize(per_cam[:2], quats, scales, opac, colors, viewmats, Ks, W, H)


def test_gradcheck_float64():
    W, H = 10, 8
    means, quats, scales, opac, colors, viewmats, Ks = random_scene(3, 4, 2, W, H)
    # Place the splats in the middle of small images, wide enough to overlap.
    means = means * 0.5
    scales = scales * 2 + 0.3
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    inputs = [x.clone().requires_grad_(True) for x in (means, quats, scales, opac, colors)]

    def render(m, q, s, o, c):
        return rasterize(m, q, s, o, c, viewmats, Ks, W, H, background=bg, tile_size=4)

    assert float(render(*inputs)[1].detach().mean()) > 0.3
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-6)

    # Precomputed covariances and SH colours (the MANUS-Hand path) are differentiable too.
    cov = covariance(quats, scales).clone().requires_grad_(True)
    sh = (torch.randn(4, 4, 3, dtype=torch.float64) * 0.3).requires_grad_(True)

    def render_cov(m, cv, o, k):
        return rasterize(m, None, None, o, k, viewmats, Ks, W, H, covars=cv, sh_degree=1)

    assert torch.autograd.gradcheck(render_cov, [inputs[0], cov, inputs[3], sh], eps=1e-6, atol=1e-6,
                                    fast_mode=True)


def test_meta_and_backends():
    W, H = 20, 16
    scene = random_scene(4, 12, 2, W, H, torch.float32)
    rgb, alpha, meta = rasterize(*scene, W, H, return_meta=True)
    assert meta["means2d"].shape == (2, 12, 2) and meta["radii"].shape == (2, 12, 2)
    assert bool((meta["radii"][meta["visible"]] > 0).all())
    auto, _ = rasterize(*scene, W, H, backend="auto")
    assert torch.equal(auto, rgb)  # on the CPU "auto" is the torch backend
    with pytest.raises(RuntimeError, match="gsplat backend needs"):
        rasterize(*scene, W, H, backend="gsplat")
