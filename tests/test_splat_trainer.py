"""The object trainer on a known scene, surfels on a sphere, and checkpoints."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

from manus_capture.splat.checkpoint import load_checkpoint, save_checkpoint
from manus_capture.splat.gaussians import Gaussians, quat_to_rotmat, quats_facing
from manus_capture.splat.losses import load_lpips
from manus_capture.splat.optimize import LearningRates
from manus_capture.splat.reference import render_reference
from manus_capture.splat.strategy import DensifyStrategy
from manus_capture.splat.trainer import ObjectConfig, Views, evaluate, hull_surface, init_points, render, train_object
from manus_core.errors import CheckpointError


def look_at(centre: torch.Tensor) -> torch.Tensor:
    """World-to-camera 4x4 of a camera at `centre` looking at the origin, z up."""
    z = -centre / centre.norm()
    x = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0]), z)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])
    V = torch.eye(4)
    V[:3, :3], V[:3, 3] = R, -R @ centre
    return V


def _ring_of_cameras(views: int) -> tuple[torch.Tensor, torch.Tensor]:
    """World-to-camera matrices (V,4,4) and intrinsics (V,3,3) of `views` 32x32 cameras on a wavy
    ring 2.5 from the origin, looking at it."""
    viewmats = []
    for i in range(views):
        az = 2 * math.pi * i / views
        el = 0.5 * math.sin(3 * az)
        centre = torch.tensor([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)]) * 2.5
        viewmats.append(look_at(centre))
    return torch.stack(viewmats), torch.tensor([[35.0, 0, 15.5], [0, 35.0, 15.5], [0, 0, 1]]).repeat(views, 1, 1)


@pytest.fixture(scope="module")
def known_scene():
    """24 ground-truth Gaussians seen by 14 cameras on a wavy ring, rendered by the reference."""
    g = torch.Generator().manual_seed(0)
    n = 24
    gt = ((torch.rand(n, 3, generator=g) - 0.5) * 0.6, torch.randn(n, 4, generator=g),
          torch.rand(n, 3, generator=g) * 0.08 + 0.03, torch.rand(n, generator=g) * 0.5 + 0.5,
          torch.rand(n, 3, generator=g))
    viewmats, Ks = _ring_of_cameras(14)
    images, alpha = render_reference(*gt, viewmats, Ks, 32, 32, background=torch.zeros(3))
    return Views(images.float(), Ks, viewmats, alpha[..., 0] > 0.01)


def test_object_fits_a_known_scene(known_scene):
    test = [0, 5, 10]
    train = [i for i in range(len(known_scene)) if i not in test]
    cfg = ObjectConfig(iterations=200, sh_degree=0, init_points=300, densify=None,
                       lr=LearningRates(means=1.6e-3, means_final=1.6e-5))
    # the paper's loss, LPIPS with the network make test installs (32 px: AlexNet takes 31 and more)
    result = train_object(known_scene.subset(train), cfg)
    assert result.history[-1]["lpips"] > 0
    held_out = evaluate(result.gaussians, known_scene.subset(test), lpips=load_lpips(None))
    assert held_out["psnr"] >= 30.0
    assert held_out["ssim"] >= 0.95
    assert 0 < held_out["lpips"] < 0.1
    # Training lowered the loss a lot from the random initialization.
    assert result.history[-1]["loss"] < 0.5 * result.history[0]["loss"]


def test_densification_and_mask_pruning_run_inside_training(known_scene):
    views = known_scene.subset(range(0, 14, 2))
    cfg = ObjectConfig(iterations=60, sh_degree=1, sh_increase_every=30,
                       densify=DensifyStrategy(refine_start_iter=20, refine_every=20, reset_every=1000),
                       lr=LearningRates(means=1.6e-3, means_final=1.6e-5))
    points, colours = init_points(views, 150, torch.Generator().manual_seed(0))
    # A floater above the object, outside the visual hull of the masks.
    floater = torch.tensor([[0.0, 0.0, 0.9]])
    init = Gaussians.from_points(torch.cat([points, floater]), torch.cat([colours, torch.ones(1, 3)]), 1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = train_object(views, cfg, init=init)
    grown = sum(r.get("cloned", 0) + r.get("split", 0) for r in result.history)
    removed = sum(r.get("pruned", 0) + r.get("mask_pruned", 0) for r in result.history)
    assert grown > 0
    assert sum(r.get("mask_pruned", 0) for r in result.history) >= 1
    assert len(result.gaussians) == 151 + grown - removed
    assert float((result.gaussians.means.detach() - floater).norm(dim=-1).min()) > 0.3


def test_fast_settings_learn_a_colour_that_changes_with_the_view():
    """ObjectConfig.fast on Gaussians whose colour changes with the view (SH degree 1, rendered by
    our rasterizer), started from their true places with other colours: it fits the training views
    and the held-out ones only by learning the view-dependent coefficients. Measured 39.4 dB on the
    training views and 30.4 held out; 32.7 and 28.1 with those coefficients stepped at 3DGS's
    twentieth of the base colour's rate from a third of the steps on, as these settings did before
    (on make demo's object: 24.40 dB held out then, 26.68 now)."""
    g = torch.Generator().manual_seed(0)
    n = 400
    points = torch.randn(n, 3, generator=g)
    points = 0.3 * points / points.norm(dim=1, keepdim=True)

    def spheres(colours: torch.Tensor) -> Gaussians:
        model = Gaussians.from_points(points, colours, 1, opacity=0.9)
        with torch.no_grad():
            model.params["scales"].fill_(math.log(0.04))
        return model

    truth = spheres(torch.rand(n, 3, generator=g) * 0.4 + 0.3)
    with torch.no_grad():
        truth.params["shN"].copy_(torch.randn(n, 3, 3, generator=g) * 0.3)
        viewmats, Ks = _ring_of_cameras(14)
        images, alpha = render(truth, viewmats, Ks, 32, 32, torch.zeros(3))
    scene = Views(images.clamp(0, 1), Ks, viewmats, alpha[..., 0] > 0.01)
    test = [0, 5, 10]
    train = [i for i in range(len(scene)) if i not in test]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = train_object(scene.subset(train), ObjectConfig.fast(400),
                              init=spheres(torch.rand(n, 3, generator=torch.Generator().manual_seed(1)) * 0.4 + 0.3))
    fitted = evaluate(result.gaussians, scene.subset(train))["psnr_mask"]
    held_out = evaluate(result.gaussians, scene.subset(test))["psnr_mask"]
    assert fitted >= 36.0 and held_out >= 29.3, (fitted, held_out)


def test_checkpoint_round_trip(tmp_path, known_scene):
    cfg = ObjectConfig(iterations=5, sh_degree=2, init_points=50, densify=None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = train_object(known_scene.subset([0, 1]), cfg).gaussians
    path = tmp_path / "object.safetensors"
    save_checkpoint(path, model, metadata={"calibration": "cameras.json"})
    loaded, extra, meta = load_checkpoint(path)
    assert meta["kind"] == "object" and meta["calibration"] == "cameras.json" and meta["sh_degree"] == "2"
    assert extra == {}
    v = known_scene
    a, _ = render(model, v.viewmats[:2], v.Ks[:2], v.width, v.height, torch.zeros(3))
    b, _ = render(loaded, v.viewmats[:2], v.Ks[:2], v.width, v.height, torch.zeros(3))
    assert torch.equal(a, b)
    # The file is safetensors: an 8-byte header length then JSON, no pickle opcodes.
    raw = path.read_bytes()
    assert raw[8:9] == b"{"


def test_checkpoint_rejects_other_files(tmp_path):
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="bad.safetensors"):
        load_checkpoint(bad)
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        load_checkpoint(tmp_path / "missing.safetensors")
    from safetensors.torch import save_file

    save_file({"x": torch.zeros(1)}, str(tmp_path / "foreign.safetensors"), metadata={"format": "other"})
    with pytest.raises(CheckpointError, match="not a manus-capture splat checkpoint"):
        load_checkpoint(tmp_path / "foreign.safetensors")


def test_reconstruct_command_trains_and_renders(tmp_path, known_scene):
    import cv2
    from click.testing import CliRunner

    from manus_capture.cli import cli
    from manus_core.cameras import CameraRig

    v = known_scene
    ids = tuple(f"c{i:02d}" for i in range(len(v)))
    rig = CameraRig(ids, v.Ks.numpy(), np.zeros((len(v), 5)), v.viewmats[:, :3, :3].numpy(),
                    v.viewmats[:, :3, 3].numpy(), np.tile([v.width, v.height], (len(v), 1)))
    rig.save(tmp_path / "cameras.json")
    for name in ("images", "masks"):
        (tmp_path / name).mkdir()
    for i, cam in enumerate(ids):
        bgr = (v.images[i].numpy()[..., ::-1] * 255 + 0.5).astype(np.uint8)
        cv2.imwrite(str(tmp_path / "images" / f"{cam}.png"), bgr)
        cv2.imwrite(str(tmp_path / "masks" / f"{cam}.png"), v.masks[i].numpy().astype(np.uint8) * 255)
    args = ["reconstruct", "object", "--cameras", str(tmp_path / "cameras.json"), "--images",
            str(tmp_path / "images"), "--masks", str(tmp_path / "masks"), "--test-cameras", "c00,c05,c10",
            "--scale", "1", "--iterations", "150", "--points", "300", "--sh-degree", "0", "--no-surfels",
            "-o", str(tmp_path / "object.safetensors")]
    runner = CliRunner()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    psnr_db = float(result.output.split("held-out PSNR ")[1].split(" dB")[0])
    assert psnr_db >= 28.0
    # the installed LPIPS scores the held-out views; it is in the loss only when asked for
    assert ", LPIPS 0." in result.output, result.output
    with_lpips = runner.invoke(cli, args[:-1] + [str(tmp_path / "lpips.safetensors"), "--lpips-loss", "0.1",
                                                 "--iterations", "20"])
    assert with_lpips.exit_code == 0 and ", LPIPS 0." in with_lpips.output, with_lpips.output

    # An existing output is not overwritten without --force: one line, exit code 2.
    again = runner.invoke(cli, args)
    assert again.exit_code == 2 and "exists" in again.output and "Traceback" not in again.output
    (tmp_path / "masks" / "c03.png").unlink()
    missing = runner.invoke(cli, args + ["--force"])
    assert missing.exit_code == 2 and "c03" in missing.output

    assert load_checkpoint(tmp_path / "object.safetensors")[2]["eps2d"] == "0.3"   # --no-surfels
    out = runner.invoke(cli, ["reconstruct", "render", str(tmp_path / "object.safetensors"), "--cameras",
                              str(tmp_path / "cameras.json"), "-o", str(tmp_path / "renders")])
    assert out.exit_code == 0, out.output
    rendered = cv2.imread(str(tmp_path / "renders" / "c05.png"))[..., ::-1] / 255.0
    target = v.images[5].numpy()
    assert rendered.shape == target.shape
    assert -10 * np.log10(np.mean((rendered - target) ** 2)) >= 28.0

# --- surfels: flat Gaussians whose centres stay on the surface they draw (what contacts measure)

RADIUS = 0.3
SIZE = 64


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
        g.params["scales"].fill_(0.0)
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
        g = train_object(views, config).gaussians
    opaque = g.opacities.detach() > 0.5
    return (g.means.detach()[opaque].norm(dim=-1) - RADIUS).numpy()


def test_surfel_centres_stay_on_the_surface_round_ones_sink(sphere):
    """Round Gaussians fill the sphere (measured: a median 103 mm inside its surface); surfels stay
    on it, within the visual hull's own erosion of a fraction of a pixel (measured: 15 mm inside,
    a pixel being 29 mm on the sphere)."""
    surfels = _centre_offsets(ObjectConfig.surfels(300, init_points=2000, max_scale=0.02, thin=0.002), sphere)
    round_ = _centre_offsets(ObjectConfig.fast(300, init_points=2000), sphere)
    assert abs(float(np.median(surfels))) < 0.02, np.percentile(surfels, [10, 50, 90])
    assert float(np.median(round_)) < -0.05, np.percentile(round_, [10, 50, 90])
