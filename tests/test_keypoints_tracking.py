"""detect's tracker (keypoints2d.track_frames): where the palm detector looks, what is found, and
that a camera split into whole redetection periods gives the keypoints of one pass.

The detector here is a stand-in whose hand is a white square: its palm detector finds the square
anywhere in a frame, its keypoint model only inside the crop it is given. What is tested is the
tracker's bookkeeping; tests/test_annotate_detect.py runs the real models on rendered hands.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from dataset_tools.keypoints.keypoints2d import _empty, track_frames

# joints on circles round the hand's centre, so that the crop around them has a size
_ANGLES = np.linspace(0, 2 * np.pi, 21, endpoint=False)
_OFFSETS = np.stack([np.cos(_ANGLES), np.sin(_ANGLES)], -1) * np.linspace(3, 9, 21)[:, None]


def _frames(n: int, present) -> list[tuple[int, np.ndarray]]:
    """Frames 96x64 with the square (5 px, moving 1 px a frame) where present(k); pixel (0, 0)
    holds the frame's number for the stand-in to log."""
    out = []
    for k in range(n):
        image = np.full((64, 96, 3), 90, np.uint8)
        if present(k):
            image[30:35, 20 + k:25 + k] = 255
        image[0, 0] = k
        out.append((k, image))
    return out


class _SquareHand:
    model = SimpleNamespace(crop=SimpleNamespace(box_scale=1.0))

    def __init__(self) -> None:
        self.palm_frames: list[int] = []

    @staticmethod
    def _centre(image: np.ndarray) -> np.ndarray | None:
        ys, xs = np.nonzero(image[1:, :, 0] > 200)
        return np.array([xs.mean(), ys.mean() + 1]) if len(xs) else None

    @staticmethod
    def _hand(centre: np.ndarray | None) -> np.ndarray:
        kp = np.full((21, 3), np.nan)
        kp[:, 2] = 0.0
        if centre is not None:
            kp[:, :2], kp[:, 2] = centre + _OFFSETS, 1.0
        return kp

    def find_boxes(self, images, max_hands, min_score):
        self.palm_frames += [int(im[0, 0, 0]) for im in images]
        centres = [self._centre(im) for im in images]
        boxes = [np.zeros((0, 4)) if c is None else np.r_[c - 10, c + 10][None] for c in centres]
        return boxes, [np.zeros(len(b)) for b in boxes]

    def detect_many(self, images, boxes, angles):
        return [self._hand(self._inside(im, (b[0, :2] + b[0, 2:]) / 2, b[0, 2] - b[0, 0]))[None]
                for im, b in zip(images, boxes)]

    def detect_rects(self, images, rects, refine=None):
        return [self._hand(self._inside(im, r[0, :2], r[0, 2]))[None] for im, r in zip(images, rects)]

    def _inside(self, image: np.ndarray, centre: np.ndarray, side: float) -> np.ndarray | None:
        found = self._centre(image)
        return found if found is not None and np.all(np.abs(found - centre) < side / 2) else None


def _track(frames, redetect_every: int, search_every: int = 8) -> tuple[np.ndarray, np.ndarray, list[int]]:
    detector = _SquareHand()
    kp, used = _empty(len(frames))
    track_frames(detector, iter(frames), 0.5, kp, used, redetect_every, search_every)
    return kp, used, detector.palm_frames


@pytest.mark.parametrize("present, palm_frames", [
    # looking at one frame in 8 while no hand is found:
    # the hand comes into view at frame 13: the palm detector looks at 0 and 8, then at 15 (the last
    # frame before the period ends), finds it there and fills 14 and 13 back; afresh at 16 and 32
    (lambda k: k >= 13, [0, 8, 15, 16, 32]),
    # lost at 20 (looked at once), not there at 24 (one frame in 8), back at 26: found at 31 before
    # the period ends and filled back to 26
    (lambda k: not 20 <= k < 26, [0, 16, 20, 24, 31, 32]),
])
def test_the_palm_detector_looks_sparsely_and_no_frame_with_the_hand_is_lost(present, palm_frames) -> None:
    frames = _frames(40, present)
    kp, used, palm = _track(frames, redetect_every=16)
    assert palm == palm_frames
    found = kp[:, 0, 2] >= 0.5
    np.testing.assert_array_equal(found, [present(k) for k in range(40)])
    # every found frame's joints on its own square, the boxes it was cropped from around them
    centres = np.array([[22.0 + k, 32.0] for k in range(40)])
    np.testing.assert_allclose(kp[found, :, :2], centres[found, None] + _OFFSETS, atol=1e-9)
    assert np.isfinite(used[found, :4]).all()
    assert np.isnan(kp[~found, :, :2]).all()


def test_a_camera_split_into_whole_periods_gives_the_keypoints_of_one_pass() -> None:
    frames = _frames(40, lambda k: k >= 13 and not 27 <= k < 30)
    whole, whole_used, _ = _track(frames, redetect_every=8)
    parts = [_track([(k - start, im) for k, im in frames[start:start + 16]], redetect_every=8)
             for start in (0, 16, 32)]
    np.testing.assert_array_equal(np.concatenate([p[0] for p in parts]), whole)
    np.testing.assert_array_equal(np.concatenate([p[1] for p in parts]), whole_used)
    # and a split that cuts a period would not: the tracker starts afresh where a task starts
    with pytest.raises(AssertionError):
        cut = [_track([(k - start, im) for k, im in frames[start:start + 12]], redetect_every=8)
               for start in (0, 12, 24, 36)]
        np.testing.assert_array_equal(np.concatenate([p[1] for p in cut]), whole_used)
