"""A take whose videos are shorter than frames.csv says (a recorder that crashed mid-take, a copy
cut short): every stage that reads frames uses those that exist and names, per camera, the
frames that are missing, instead of stopping at the first one."""

from __future__ import annotations

import os
import warnings

import cv2
import numpy as np
import pytest
from test_keypoints_take import _BoxDetector, _frames, make_take

from dataset_tools.keypoints.keypoints2d import detect_take, detect_take_tasks
from dataset_tools.segmentation.takes import segment_take
from manus_core.cameras import CameraRig
from manus_core.matroska import MatroskaVideo
from manus_core.take import Take

FRAMES, KEPT = 40, 29


def cut_after(path, frames: int) -> None:
    """Cut a video in the middle of frame `frames` (0-based), as a crash while writing it would."""
    with MatroskaVideo(path) as video:
        data, _ = list(video._blocks(video.first_cluster, 0))[frames]
    os.truncate(path, data + 10)


@pytest.fixture()
def cut_take(tmp_path):
    rng = np.random.default_rng(0)
    scene = cv2.GaussianBlur(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8), (0, 0), 2)
    make_take(tmp_path / "empty", {"a": [scene] * 3, "b": [scene] * 3})
    make_take(tmp_path / "take", {"a": _frames(FRAMES), "b": _frames(FRAMES, seed=1)})
    cut_after(tmp_path / "take" / "cams" / "b.mkv", KEPT)
    return tmp_path


def test_the_take_names_the_missing_frames_by_camera(cut_take):
    take = Take(cut_take / "take")
    assert take.missing_frames() == {"b": (KEPT, FRAMES)}
    assert take.readable_frames("a") == FRAMES and take.readable_frames("b") == KEPT
    (note,) = take.missing_notes()
    assert note.startswith(f"camera b: b.mkv holds {KEPT} of its {FRAMES} frames.csv rows")
    assert f"frames {KEPT}-{FRAMES - 1} have no image" in note


def test_detect_uses_the_frames_that_exist(cut_take):
    take = Take(cut_take / "take")
    boxes = {cam: np.tile([0.0, 0.0, 8.0, 4.0, np.nan], (FRAMES, 1)) for cam in take.cameras}
    result = detect_take(take, _BoxDetector(), boxes, chunk=8)
    found = {cam: r.keypoints[:, 0, 2] > 0.5 for cam, r in result.items()}
    assert found["a"].all()
    assert found["b"][:KEPT].all() and not found["b"][KEPT:].any()
    assert result["b"].keypoints.shape == (FRAMES, 21, 3)        # rows stay frames.csv's
    tasks = detect_take_tasks(take, "mediapipe-hand", boxes=boxes, chunk=8, frames_per_task=16)
    assert max(t.stop for t in tasks if t.camera == "b") == KEPT
    assert max(t.stop for t in tasks if t.camera == "a") == FRAMES


def test_segment_leaves_the_missing_views_out_and_says_so(cut_take):
    rig = CameraRig(("a", "b"), np.tile([[60.0, 0, 31.5], [0, 60, 23.5], [0, 0, 1]], (2, 1, 1)), np.zeros((2, 5)),
                    np.tile(np.eye(3), (2, 1, 1)), [[0, 0, 0], [0.2, 0, 0]], [[64, 48]] * 2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = segment_take(cut_take / "take", rig, cut_take / "empty")
    b = result.cameras.index("b")
    assert len(result.frame_index) == FRAMES
    assert (result.frame_index[KEPT:, b] == -1).all() and (result.frame_index[:KEPT, b] >= 0).all()
    assert any(w.startswith(f"camera b: b.mkv holds {KEPT} of its {FRAMES}") for w in result.report["warnings"])
