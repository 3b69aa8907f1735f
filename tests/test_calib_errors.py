"""Bad input: every message names the cameras (or the file and key) and what is likely wrong."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from dataset_tools.calibration.board_rig import calibrate_board_rig
from dataset_tools.calibration.boards import board_from_dict, tags_from_dict
from dataset_tools.calibration.detect import Detection, detect_source
from dataset_tools.calibration.frames import FrameSource, read_frames
from dataset_tools.calibration.rig import calibrate_rig
from dataset_tools.calibration.tag_rig import calibrate_tag_rig
from manus_core.cameras import CameraRig
from manus_core.errors import BoardError, CalibrationError, DetectionError, ExtrinsicsError

CHARUCO = board_from_dict({"type": "charuco", "cols": 4, "rows": 5, "square": 0.054, "marker": 0.0405,
                           "dictionary": "DICT_4X4_1000", "inverted": True})


@pytest.fixture(scope="module")
def frames(shared_data):
    """12 evenly spread frames of each caliscope camera, in memory (same instants in every camera)."""
    root = shared_data / "caliscope_4cam_charuco" / "calibration" / "extrinsic"
    picks = tuple(range(2, 57, 5))
    return {str(c): [g for _, g in read_frames(FrameSource((str(root / f"cam_{c}.mp4"),), picks))] for c in range(4)}


@pytest.mark.parametrize("change, hint", [
    (dict(inverted=False), "inverted = true"),
    (dict(cols=5, rows=4), "cols = 4, rows = 5 (cols and rows swapped)"),
    (dict(cols=3, rows=4), "cols = 4, rows = 5 (a charuco board's cols and rows count squares)"),
    (dict(dictionary="DICT_5X5_1000"), 'set dictionary = "DICT_4X4_1000"'),
])
def test_board_that_matches_nothing_says_which_parameter(frames, change, hint):
    wrong = replace(CHARUCO, **change)
    with pytest.raises(BoardError) as err:
        calibrate_rig({c: f[:4] for c, f in frames.items()}, board=wrong, workers=1)
    message = str(err.value)
    assert "no camera sees the board (0, 1, 2, 3)" in message and hint in message


def test_too_few_detections_and_allow_partial(frames):
    images = dict(frames)
    images["3"] = frames["3"][:2]  # the board in two frames only
    with pytest.raises(CalibrationError, match=r"1 of 4 cameras cannot be calibrated \(camera 3: the board is found in [0-3] frame"):
        calibrate_rig(images, board=CHARUCO, workers=1)
    result = calibrate_rig(images, board=CHARUCO, allow_partial=True, workers=1)
    assert result.partial and set(result.missing) == {"3"} and result.rig.ids == ("0", "1", "2")
    assert result.rms_px < 2.0


def test_mixed_image_sizes_name_the_camera(frames):
    images = {c: list(f[:5]) for c, f in frames.items()}
    images["2"][3] = images["2"][3][:480, :640]
    with pytest.raises(DetectionError, match=r"camera 2: image 3: image size 640x480 differs from 1280x720"):
        calibrate_rig(images, board=CHARUCO, workers=1)


def test_unreadable_and_mixed_files(tmp_path):
    bad = tmp_path / "x.jpg"
    bad.write_bytes(b"not a jpeg")
    with pytest.raises(DetectionError, match="x.jpg: not a readable image"):
        detect_source(FrameSource((str(bad),)), CHARUCO)


def test_chessboards_cannot_place_several_cameras():
    board = board_from_dict({"type": "chessboard", "cols": 9, "rows": 6, "square": 0.025, "inverted": False})
    with pytest.raises(ExtrinsicsError, match="chessboard looks the same turned by 180 degrees"):
        calibrate_board_rig({"a": {}, "b": {}}, {"a": (640, 480), "b": (640, 480)}, board)


def _tag_scene():
    """Two walls of 2x2 tags and three cameras looking at them (exact projections)."""
    corners = {}
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]]) * 0.2
    for k in range(4):
        u, v = (square + [0.3 * (k % 2), 0.3 * (k // 2)]).T
        corners[str(k)] = np.stack([u, np.full(4, 1.0), 1.2 - v], 1).tolist()          # wall y = 1
        corners[str(k + 4)] = np.stack([np.full(4, 1.0), 1.0 - u, 1.2 - v], 1).tolist()  # wall x = 1
    layout = tags_from_dict({"family": "tag36h11", "size": 0.2, "tags": corners})
    K = np.array([[600.0, 0, 319.5], [0, 600, 239.5], [0, 0, 1]])
    centres = np.array([[-0.6, -0.5, 0.5], [-0.2, -0.7, 0.6], [-0.7, 0.0, 0.4]])
    Rs = []
    for c in centres:  # look at (0.5, 0.5, 0.6), z up
        z = np.array([0.5, 0.5, 0.6]) - c
        z /= np.linalg.norm(z)
        x = np.cross(z, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        Rs.append(np.stack([x, np.cross(z, x), z]))
    Rs = np.array(Rs)
    rig = CameraRig(("a", "b", "c"), [K] * 3, np.zeros((3, 5)), Rs, -np.einsum("cij,cj->ci", Rs, centres),
                    [[640, 480]] * 3)
    return layout, rig


def _detections(layout, rig, noise_px=0.0, seed=0):
    pid, world = layout.points()
    uv = rig.project(world) + np.random.default_rng(seed).normal(0, noise_px, (len(rig), len(pid), 2))
    return {c: {0: Detection(pid, uv[i])} for i, c in enumerate(rig.ids)}


def test_tag_bundle_adjustment_recovers_cameras():
    layout, truth = _tag_scene()
    dets = _detections(layout, truth, noise_px=0.1)
    intr = {c: (truth.K[i], truth.dist[i]) for i, c in enumerate(truth.ids)}
    result = calibrate_tag_rig(dets, {c: (640, 480) for c in truth.ids}, layout, intr)
    assert np.linalg.norm(result.rig.centers - truth.centers, axis=1).max() < 0.002
    assert 0.05 < result.rms_px < 0.15  # fits to the noise, not below it


def test_camera_that_sees_no_tag():
    layout, truth = _tag_scene()
    dets = _detections(layout, truth)
    dets["c"] = {0: Detection(np.arange(8) + 400, dets["c"][0].xy[:8])}  # tags 100 and 101: not in the layout
    intr = {c: (truth.K[i], truth.dist[i]) for i, c in enumerate(truth.ids)}
    sizes = {c: (640, 480) for c in truth.ids}
    with pytest.raises(ExtrinsicsError, match=r"camera c: sees no tag of tags.json .*--allow-partial"):
        calibrate_tag_rig(dets, sizes, layout, intr)
    result = calibrate_tag_rig(dets, sizes, layout, intr, allow_partial=True)
    assert result.partial and result.rig.ids == ("a", "b") and "c" in result.missing


def test_method_needs_its_inputs(frames):
    with pytest.raises(CalibrationError, match="needs a tag layout"):
        calibrate_rig(frames, board=CHARUCO, method="both")
    with pytest.raises(CalibrationError, match="either per-camera images or a take folder"):
        calibrate_rig(None, board=CHARUCO)
