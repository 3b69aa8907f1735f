"""manus_capture.api: the low-level pieces against their contracts, errors and progress, and a
check that every exported name is exercised. The pipeline functions run in tests/test_demo.py on
the demo's simulated session (recording it again here would double the suite's longest fixture)."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import torch

from manus_capture import api
from rig.layouts import make_rig
from rig.sim.cube import true_cameras

TESTS = Path(__file__).parent


def test_camera_rig_and_triangulate_round_trip(tmp_path):
    cams = true_cameras(make_rig("cube53", cameras=8, resolution=(640, 360)))
    api.save_cameras(cams, tmp_path / "cameras.json")
    rig = api.load_cameras(tmp_path / "cameras.json")
    assert isinstance(rig, api.CameraRig) and rig.ids == cams.ids
    X = np.random.default_rng(0).uniform(-0.1, 0.1, (50, 3))
    uv = rig.project(X)
    points2d = np.concatenate([uv, np.ones((8, 50, 1))], axis=2)
    points, error = api.triangulate(rig, points2d)
    assert np.abs(points - X).max() < 1e-6 and error.max() < 1e-3
    undistorted = api.undistort_points(rig, uv)
    Xc = rig.to_camera(X)
    np.testing.assert_allclose(undistorted, Xc[..., :2] / Xc[..., 2:], atol=1e-9)


def test_one_euro_skeleton_and_fit():
    t = np.arange(100) / 120.0
    x = np.sin(t)[:, None].repeat(3, axis=1)
    assert api.one_euro(x, t).shape == (100, 3)
    skeleton = api.HandSkeleton()
    angles = np.zeros((4, 26))
    angles[:, 6::4] = 0.3
    joints = skeleton.forward(angles)
    fitted_angles, fitted = api.fit_hand(joints)
    assert np.abs(fitted - joints).max() < 1e-4 and fitted_angles.shape == (4, 26)


def test_rasterize_contract():
    n = 5
    rgb, alpha = api.rasterize(torch.zeros(n, 3) + torch.tensor([0.0, 0.0, 2.0]), torch.tensor([[1.0, 0, 0, 0]] * n),
                               torch.full((n, 3), 0.05), torch.full((n,), 0.9), torch.rand(n, 3),
                               torch.eye(4)[None], torch.tensor([[[50.0, 0, 16], [0, 50.0, 16], [0, 0, 1]]]), 32, 32)
    assert rgb.shape == (1, 32, 32, 3) and alpha.shape == (1, 32, 32, 1)
    assert alpha[0, 16, 16, 0] > 0.5 and alpha[0, 0, 0, 0] < 0.01


def test_errors_carry_their_exit_code(tmp_path):
    try:
        api.load_cameras(tmp_path / "nothing.json")
    except api.InputError as exc:
        assert isinstance(exc, api.ManusError) and exc.exit_code == 2 and str(tmp_path / "nothing.json") in str(exc)
    else:
        raise AssertionError("a missing calibration file was accepted")


def test_every_exported_name_is_exercised():
    """The api's names are exactly those this file and test_demo.py call or check."""
    used = set()
    for name in ("test_api.py", "test_demo.py"):
        tree = ast.parse((TESTS / name).read_text())
        used |= {node.attr for node in ast.walk(tree) if isinstance(node, ast.Attribute)
                 and isinstance(node.value, ast.Name) and node.value.id == "api"}
    assert used - {"__all__"} == set(api.__all__)
