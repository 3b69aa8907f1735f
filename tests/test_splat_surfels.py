"""Surfels: flat Gaussians whose centres stay on the surface they draw (what contacts measure)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

from manus_capture.splat.gaussians import Gaussians, quat_to_rotmat, quats_facing
from manus_capture.splat.trainer import ObjectConfig, Views, hull_surface, train_object

RADIUS = 0.3
SIZE = 64


def look_at(centre: torch.Tensor) -> torch.Tensor:
    """World-to-camera 4x4 of a camera at `centre` looking at the origin, z up."""
    z = -centre / centre.norm()
    x = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0]), z)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    V = torch.eye(4)
    V[:3, :3] = torch.stack([x, y, z])
    V[:3, 3] = -V[:3, :3] @ centre
    return V


@pytest.fixture(scope="module")
def sphere() -> Views:
    """A shaded sphere of radius RADIUS at the origin, ray-traced (4x4 samples per pixel, so edge
    pixels are the mix a camera sees) into 16 cameras around it, with masks of the majority."""
    viewmats = []
    for i in range(16):
        az, el = 2 * math.pi * i / 16, 0.6 * math.sin(2 * math.pi * i / 16 * 3)
        viewmats.append(look_at(torch.tensor([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el),
                                              math.sin(el)]) * 2.0))
    viewmats = torch.stack(viewmats)
    K = torch.tensor([[70.0, 0, (SIZE - 1) / 2], [0, 70.0, (SIZE - 1) / 2], [0, 0, 1]])
    sub = (torch.arange(4) + 0.5) / 4 - 0.5
    pix = torch.arange(SIZE, dtype=torch.float32)
    ys = (pix[:, None] + sub[None]).reshape(-1)
    gy, gx = torch.meshgrid(ys, ys, indexing="ij")
    rays = torch.stack([(gx - K[0, 2]) / K[0, 0], (gy - K[1, 2]) / K[1, 1], torch.ones_like(gx)], -1)
    images, masks = [], []
    for V in viewmats:
        R, t = V[:3, :3], V[:3, 3]
        centre = -R.T @ t
        d = rays @ R  # world directions (R^T r)
        d = d / d.norm(dim=-1, keepdim=True)
        b = (d * centre).sum(-1)
        disc = b * b - (centre @ centre - RADIUS ** 2)
        hit = disc > 0
        s = -b - disc.clamp_min(0).sqrt()
        normal = (centre + s[..., None] * d) / RADIUS
        shade = 0.35 + 0.6 * (normal @ torch.tensor([0.3, 0.4, 0.866])).clamp_min(0)
        colour = torch.stack([shade, 0.8 * shade, 0.6 * shade], -1) * hit[..., None]
        block = colour.reshape(SIZE, 4, SIZE, 4, 3).mean(dim=(1, 3))
        images.append(block)
        masks.append(hit.float().reshape(SIZE, 4, SIZE, 4).mean(dim=(1, 3)) > 0.5)
    return Views(torch.stack(images), K.expand(16, 3, 3).clone(), viewmats, torch.stack(masks))


def test_quats_facing_turn_the_third_axis_to_the_normal():
    normals = torch.cat([torch.randn(200, 3), torch.tensor([[0, 0, 1.0], [0, 0, -1.0], [1e-9, 0, -1.0]])])
    third = quat_to_rotmat(quats_facing(normals))[:, :, 2]
    assert torch.allclose(third, normals / normals.norm(dim=-1, keepdim=True), atol=1e-5)


def test_surfels_are_discs_facing_their_normals_and_stay_thin():
    points, normals = torch.randn(50, 3), torch.randn(50, 3)
    g = Gaussians.surfels(points, normals, thin=1e-3)
    assert torch.all(g.scales[:, 2] <= 1e-3 + 1e-9) and torch.all(g.scales[:, :2] > 0.1)
    with torch.no_grad():
        g.params["log_scales"].fill_(0.0)
    g.cap_scales(max_scale=0.5, thin=1e-3)
    assert torch.allclose(g.scales[:, :2], torch.full((50, 2), 0.5))
    assert torch.allclose(g.scales[:, 2], torch.full((50,), 1e-3))


def test_hull_surface_points_face_out_of_the_sphere(sphere):
    points, normals, colours = hull_surface(sphere, 2000, torch.Generator().manual_seed(0))
    r = points.norm(dim=-1)
    # the visual hull of 16 views is a little larger than the sphere; the points are within the
    # step that finds the boundary (2 % of the hull box's diagonal, 0.022 here, along an axis, so
    # up to sqrt(3) times that along the normal) of it
    assert float(r.min()) > RADIUS - 0.04 and float(r.max()) < RADIUS + 0.03, (float(r.min()), float(r.max()))
    facing = (normals * points / r[:, None]).sum(-1)
    assert float((facing > 0.9).float().mean()) > 0.9
    assert float(colours.max()) > 0.3


def _centre_offsets(config: ObjectConfig, views: Views) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # LPIPS is off without weights
        g = train_object(views, config, progress=False).gaussians
    opaque = g.opacities.detach() > 0.5
    return (g.means.detach()[opaque].norm(dim=-1) - RADIUS).numpy()


def test_surfel_centres_stay_on_the_surface_round_ones_sink(sphere):
    """Round Gaussians fill the sphere (measured: a median 103 mm inside its surface); surfels stay
    on it, within the visual hull's own erosion of a fraction of a pixel (measured: 16 mm inside,
    a pixel being 29 mm on the sphere)."""
    surfels = _centre_offsets(ObjectConfig.surfels(300, init_points=2000, max_scale=0.02, thin=0.002), sphere)
    round_ = _centre_offsets(ObjectConfig.fast(300, init_points=2000), sphere)
    assert abs(float(np.median(surfels))) < 0.02, np.percentile(surfels, [10, 50, 90])
    assert float(np.median(round_)) < -0.05, np.percentile(round_, [10, 50, 90])
