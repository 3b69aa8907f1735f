"""Real 4-camera ChArUco session (caliscope): the whole board pipeline against caliscope's result.

The metric is computed on caliscope's own 2D observations (CHARUCO/xy_CHARUCO.csv), so that our
calibration and caliscope's reference calibration (camera_array.toml) are scored on exactly the
same points: triangulate each (frame, corner) from all cameras that saw it, reproject, and measure
the distance between neighbouring corners of the 54 mm board.
"""

from __future__ import annotations

import csv
import tomllib

import numpy as np
import pytest

from dataset_tools.calibration.boards import board_from_dict
from dataset_tools.calibration.report import scale_check, triangulation_check
from dataset_tools.calibration.rig import calibrate_rig
from manus_core.cameras import CameraRig

SQUARE = 0.054
BOARD = {"type": "charuco", "cols": 4, "rows": 5, "square": SQUARE, "marker": 0.75 * SQUARE,
         "dictionary": "DICT_4X4_1000", "inverted": True}


def reference_observations(root) -> np.ndarray:
    """rows of (sync_index, cam, corner id, x, y) from caliscope's detections."""
    with open(root / "calibration/extrinsic/CHARUCO/xy_CHARUCO.csv") as f:
        rows = list(csv.DictReader(f))
    return np.array([[int(r["sync_index"]), int(r["cam_id"]), int(r["keypoint_id"]), float(r["img_loc_x"]),
                      float(r["img_loc_y"])] for r in rows])


def reference_rig(root) -> CameraRig:
    doc = tomllib.loads((root / "camera_array.toml").read_text())["cameras"]
    cams = [doc[str(c)] for c in range(4)]
    return CameraRig(tuple(str(c) for c in range(4)), [c["matrix"] for c in cams], [c["distortions"] for c in cams],
                     [c["rotation"] for c in cams], [c["translation"] for c in cams], [c["size"] for c in cams])


def score(rig: CameraRig, obs: np.ndarray) -> dict:
    """Triangulate the reference observations with `rig`: reprojection RMSE and corner distances."""
    board = board_from_dict(BOARD)
    return triangulation_check(rig.subset(["0", "1", "2", "3"]), obs[:, 1].astype(int), obs[:, 0].astype(int),
                               obs[:, 2].astype(int), obs[:, 3:5], board.neighbour_pairs(), SQUARE)


@pytest.fixture(scope="module")
def session(shared_data):
    return shared_data / "caliscope_4cam_charuco"


@pytest.fixture(scope="module")
def calibration(session):
    videos = {str(c): session / f"calibration/extrinsic/cam_{c}.mp4" for c in range(4)}
    return calibrate_rig(videos, board=board_from_dict(BOARD), workers=1)


def test_reference_scoring_reproduces_published_numbers(session):
    # SOURCES.md: caliscope's calibration gives RMSE 1.6376 px and 53.85 mm on these points
    check = score(reference_rig(session), reference_observations(session))
    assert check["rmse_px"] == pytest.approx(1.6376, abs=2e-3)
    assert check["median_px"] == pytest.approx(1.0174, abs=2e-3)
    assert check["mean_m"] * 1000 == pytest.approx(53.85, abs=0.02)
    assert check["std_m"] * 1000 == pytest.approx(0.81, abs=0.02)


def test_four_cameras_from_videos_beat_the_reference(session, calibration):
    assert sorted(calibration.rig.ids) == ["0", "1", "2", "3"] and not calibration.partial
    check = score(calibration.rig, reference_observations(session))
    assert abs(check["mean_m"] - SQUARE) < 0.0005, f"mean neighbour distance {check['mean_m'] * 1000:.2f} mm"
    assert check["rmse_px"] <= 1.6376, f"reprojection RMSE {check['rmse_px']:.3f} px (caliscope 1.638)"
    assert check["points"] == 660  # every reference point is triangulated


def test_bundle_adjustment_fits_and_scale_check(calibration):
    board = board_from_dict(BOARD)
    check = scale_check(calibration, board.neighbour_pairs(), board.neighbour_distance())
    assert abs(check["error_pct"]) < 1.0 and check["pairs"] > 500
    # every camera's own detections fit to about a pixel (webcams, 6 fps, frames ~10 ms apart)
    assert all(s.rms_px < 2.0 and s.observations > 300 for s in calibration.stats.values())
    assert calibration.rms_px < 1.3
