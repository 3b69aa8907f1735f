"""Simulated cube (16 of the 53 cameras, 640x360): tags + COLMAP against the true cameras.

The full 53-camera check on a recorded simulated take belongs to the end-to-end tests; this one
renders the empty cube directly, so it checks the calibration alone, with exact ground truth.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from dataset_tools.calibration.boards import tags_from_dict
from dataset_tools.calibration.rig import calibrate_rig
from manus_core.rotations import rotation_angle_deg
from rig.layouts import make_rig
from rig.sim.cube import true_cameras
from rig.sim.render import Renderer
from rig.sim.world import World


@pytest.fixture(scope="module")
def scene():
    truth = true_cameras(make_rig(cameras=16, resolution=(640, 360), seed=1))
    world = World(tags_per_wall=8, tag_size=0.09)   # the density docs/calibration.md advises
    renderer = Renderer(world, truth, supersample=2)
    images = {c: [(renderer.background(i)[0] * 255).round().astype(np.uint8)] for i, c in enumerate(truth.ids)}
    return truth, tags_from_dict(world.tags_json()), images


def test_tags_and_colmap_recover_the_true_poses_given_the_true_intrinsics(scene, tmp_path):
    truth, layout, images = scene
    result = calibrate_rig(images, tags=layout, intrinsics=truth, method="both", workers=1, output=tmp_path)
    assert not result.partial and set(result.rig.ids) == set(truth.ids)
    est, ref = result.rig, truth.subset(result.rig.ids)
    centre_mm = np.linalg.norm(est.centers - ref.centers, axis=1) * 1000
    assert centre_mm.max() < 2.0, dict(zip(est.ids, centre_mm.round(2)))
    assert rotation_angle_deg(est.R, ref.R).max() < 0.1
    assert result.median_px < 0.3
    report = json.loads((tmp_path / "report.json").read_text())
    assert abs(report["checks"]["scale"]["error_pct"]) < 0.1
    # COLMAP registers the cameras and its model fits the tag layout to millimetres; its camera
    # poses alone are centimetre-level here (640x360, walls seen at up to 90 degrees apart)
    assert report["inputs"]["colmap"]["registered"] >= 12
    assert report["inputs"]["colmap"]["alignment_rms_mm"] < 5
    assert len(report["checks"]["cross_check"]["cameras"]) == 16
