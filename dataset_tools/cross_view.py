"""Keypoints in the views where the palm detector found no hand, from the hand the other views see.

MediaPipe's palm detector misses hands that are small in the frame, seen edge-on or half hidden
by the object: in `make demo` (24 cameras at 320x180) it finds the hand in 31 % of the grasp's
views. The landmark model, given a crop around a hand, finds it in many more; MediaPipe's tracker
uses that from one frame to the next, and a calibrated rig can do it from one view to the others.
Where the views that found the hand triangulate enough of its joints, those joints projected into
a view that found nothing give the crop around the hand there (`boxes.rects_from_keypoints`, as
the tracker crops around the last frame's keypoints). The landmark model runs on that crop, once
more on the crop around its own keypoints, and what it finds is kept where it says a hand is there
(presence >= min_score) and its keypoints lie near the projection (median distance under
`max_offset` of the crop's side): a crop on the object with the hand hidden behind it gives low
presence or keypoints elsewhere.

Frames are read per camera in increasing order, only those asked for and a chunk at a time
(`Take.stream_frames`), so the cost follows the views recovered and the memory does not grow with
the take.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from manus_core.cameras import CameraRig
from manus_core.take import Take

from .keypoints import Detector
from .keypoints import boxes as bx
from .triangulation import triangulate_frames


@dataclass(frozen=True)
class CrossViewOptions:
    """min_joints: joints a frame group must triangulate for its hand to be projected; min_inside:
    projected joints that must land inside a view's image; min_score: the landmark model's hand
    presence to keep what it finds; max_offset: the largest median distance, as a share of the
    crop's side, between what it finds and the projection; chunk: frames a network call."""

    min_joints: int = 15
    min_inside: int = 10
    min_score: float = 0.5
    max_offset: float = 0.35
    chunk: int = 32


def missing_views(keypoints2d: np.ndarray, frame_index: np.ndarray, min_score: float = 0.5) -> np.ndarray:
    """(T,C) bool: views with a frame where no hand was found (presence under min_score or NaN)."""
    kp = np.asarray(keypoints2d)
    found = (kp[..., 0, 2] >= min_score) & np.isfinite(kp[..., :2]).all(axis=(-1, -2))
    return ~found & (np.asarray(frame_index) >= 0)


def recover_views(take: Take, rig: CameraRig, keypoints2d: np.ndarray, frame_index: np.ndarray, detector: Detector,
                  threshold_px: float, min_views: int,
                  options: CrossViewOptions = CrossViewOptions()) -> tuple[np.ndarray, int]:
    """Keypoints (T,C,21,3) of the rig's cameras (its order) with the views the detector missed
    filled in where the others' hand shows it (module doc), and how many views were filled in.

    frame_index (T,C): each group's frame of each camera (-1: none). threshold_px and min_views
    are the triangulation's (AnnotateOptions').
    """
    kp = np.array(keypoints2d, dtype=np.float64)
    X, _ = triangulate_frames(rig, kp, threshold_px=threshold_px, min_views=min_views)
    seen = np.isfinite(X).all(-1).sum(-1) >= options.min_joints
    todo = missing_views(kp, frame_index, options.min_score) & seen[:, None]
    if not todo.any():
        return kp, 0
    T = len(X)
    uv = rig.project(X.reshape(-1, 3)).reshape(len(rig), T, 21, 2)       # (C,T,21,2)
    size = np.asarray(rig.size, np.float64)[:, None, None, :]
    inside = (np.isfinite(uv).all(-1) & (uv >= -0.5).all(-1) & (uv <= size - 0.5).all(-1)).sum(-1)  # (C,T)
    todo &= inside.T >= options.min_inside
    recovered = 0
    for c, cam in enumerate(rig.ids):
        # frames past the end of a video cut short (a crashed take) have no image to look at
        rows = np.flatnonzero(todo[:, c] & (frame_index[:, c] < take.readable_frames(cam)))
        if not len(rows):
            continue
        # Crop around the projected joints that are known; a NaN joint would make the crop NaN.
        projected = uv[c, rows]
        known = np.isfinite(projected).all(-1)
        centre = np.nanmean(projected, axis=1, keepdims=True)
        rects = bx.rects_from_keypoints(np.where(known[..., None], projected, centre))
        frames = frame_index[rows, c]
        by_frame: dict[int, list[int]] = {}
        for i, k in enumerate(frames):
            by_frame.setdefault(int(k), []).append(i)
        batch: list[tuple[int, np.ndarray]] = []
        for k, image in take.stream_frames(cam, frames):   # a new array each frame: batch may hold it
            batch.extend((i, image) for i in by_frame[k])
            if len(batch) >= options.chunk:
                recovered += _detect(detector, batch, rows, rects, projected, c, kp, options)
                batch = []
        if batch:
            recovered += _detect(detector, batch, rows, rects, projected, c, kp, options)
    return kp, recovered


def _detect(detector: Detector, batch: list[tuple[int, np.ndarray]], rows: np.ndarray, rects: np.ndarray,
            projected: np.ndarray, c: int, kp: np.ndarray, options: CrossViewOptions) -> int:
    """The landmark model on a batch of (index into rows, image); keeps what passes into kp[rows, c]."""
    index = np.array([i for i, _ in batch])
    found = np.concatenate(detector.detect_rects([im for _, im in batch], [rects[i][None] for i in index], refine=1))
    offset = np.nanmedian(np.linalg.norm(found[..., :2] - projected[index], axis=-1), axis=-1)
    with np.errstate(invalid="ignore"):
        keep = (found[:, 0, 2] >= options.min_score) & (offset < options.max_offset * rects[index, 2])
    kp[rows[index[keep]], c] = found[keep]
    return int(keep.sum())
