"""The public API of DESIGN.md: every name resolves and follows its documented contract."""

from __future__ import annotations

import numpy as np
import pytest

from manus_capture import api
from rig.layouts import make_rig
from rig.sim.cube import true_cameras


@pytest.fixture(scope="module")
def cams():
    return true_cameras(make_rig("cube53", cameras=8, resolution=(640, 360)))


def test_camera_rig_and_triangulate_round_trip(cams, tmp_path):
    cams.save(tmp_path / "cameras.json")
    rig = api.load_cameras(tmp_path / "cameras.json")
    assert isinstance(rig, api.CameraRig) and rig.ids == cams.ids
    X = np.random.default_rng(0).uniform(-0.1, 0.1, (50, 3))
    uv = rig.project(X)
    assert uv.shape == (8, 50, 2)
    points2d = np.concatenate([uv, np.ones((8, 50, 1))], axis=2)
    points, error = api.triangulate(rig, points2d)
    assert points.shape == (50, 3) and error.shape == (50,)
    assert np.abs(points - X).max() < 1e-6 and error.max() < 1e-3


def test_one_euro_and_skeleton_shapes():
    t = np.arange(100) / 120.0
    x = np.sin(t)[:, None].repeat(3, axis=1)
    assert api.one_euro(x, t).shape == (100, 3)
    skeleton = api.HandSkeleton()
    assert skeleton.forward(np.zeros((4, 26))).shape == (4, 21, 3)


def test_rasterize_contract():
    torch = pytest.importorskip("torch")
    n = 5
    rgb, alpha = api.rasterize(torch.zeros(n, 3) + torch.tensor([0.0, 0.0, 2.0]), torch.tensor([[1.0, 0, 0, 0]] * n),
                               torch.full((n, 3), 0.05), torch.full((n,), 0.9), torch.rand(n, 3),
                               torch.eye(4)[None], torch.tensor([[[50.0, 0, 16], [0, 50.0, 16], [0, 0, 1]]]), 32, 32)
    assert rgb.shape == (1, 32, 32, 3) and alpha.shape == (1, 32, 32, 1)
    assert alpha[0, 16, 16, 0] > 0.5 and alpha[0, 0, 0, 0] < 0.01


def test_every_documented_name_is_exported():
    for name in ["load_cameras", "CameraRig", "triangulate", "one_euro", "HandSkeleton", "fit_hand",
                 "hand_keypoint_detector", "Detector", "rasterize"]:
        assert name in api.__all__
