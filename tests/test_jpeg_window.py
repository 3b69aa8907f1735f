"""The window decoder (manus_core.jpeg_window, built by make): a window of a JPEG has the whole
decode's pixels, on real photographs of three chroma subsamplings, and detect's tracker, which
decodes only the window under each crop, finds the keypoints it finds in whole frames."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import simplejpeg
from test_keypoints_take import make_take

from dataset_tools.keypoints.detector import hand_keypoint_detector
from dataset_tools.keypoints.install import installed_manifest
from dataset_tools.keypoints.keypoints2d import _empty, detect_take, track_frames
from manus_core import jpeg_window
from manus_core.take import Take

PHOTOS = ("caliscope_4cam_charuco/aruco_extrinsic_frames/cam_0_frame_0000.jpg",   # 1280x720, 4:2:0
          "hand_samples/onehand10k/1402.jpg",                                       # 226x339, 4:2:2
          "apriltag_detection/33369213973_9d9bb4cc96_c.jpg")                        # 799x533, 4:4:4


def test_the_library_is_built() -> None:
    assert jpeg_window.available(), f"{jpeg_window.LIBRARY} is missing: `make` builds it"


@pytest.mark.parametrize("name", PHOTOS)
def test_a_window_has_the_whole_decodes_pixels_and_nothing_else_is_written(shared_data: Path, name: str) -> None:
    packet = np.fromfile(shared_data / name, np.uint8)
    whole = simplejpeg.decode_jpeg(packet, colorspace="BGR")    # the take reader's decoder
    h, w = whole.shape[:2]
    rng = np.random.default_rng(0)
    windows = [(0, 0, w, h), (0, 0, 1, 1), (w - 1, h - 1, 1, 1), (w // 3, h // 4, w // 2, h // 3)]
    for _ in range(20):
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        windows.append((x, y, int(rng.integers(1, w - x + 1)), int(rng.integers(1, h - y + 1))))
    for x, y, ww, hh in windows:
        out = np.full_like(whole, 7)
        got_x, got_w = jpeg_window.decode_window(packet, x, y, ww, hh, out)
        assert got_x <= x and x + ww <= got_x + got_w <= w, (x, ww, got_x, got_w)
        np.testing.assert_array_equal(out[y:y + hh, got_x:got_x + got_w], whole[y:y + hh, got_x:got_x + got_w])
        untouched = np.ones((h, w), bool)
        untouched[y:y + hh, max(got_x - 1, 0):got_x + got_w + 1] = False
        assert (out[untouched] == 7).all()


def test_bad_input_is_one_error(shared_data: Path) -> None:
    packet = np.fromfile(shared_data / PHOTOS[0], np.uint8)
    out = np.empty((720, 1280, 3), np.uint8)
    with pytest.raises(ValueError, match="Not a JPEG file"):
        jpeg_window.decode_window(np.zeros(100, np.uint8), 0, 0, 10, 10, out)
    with pytest.raises(ValueError, match=r"window 100x10 at \(1200, 0\) outside the 1280x720 frame"):
        jpeg_window.decode_window(packet, 1200, 0, 100, 10, out)
    with pytest.raises(ValueError, match="a 1280x720 frame for a 640x360 buffer"):
        jpeg_window.decode_window(packet, 0, 0, 10, 10, np.empty((360, 640, 3), np.uint8))


@pytest.fixture(scope="module")
def moving_hand(tmp_path_factory, shared_data: Path) -> Path:
    """A FreiHAND photo's hand moving 4 px a frame across a 640x360 frame, 12 frames: a take."""
    photo = cv2.imread(str(shared_data / "hand_samples/freihand/00000355.jpg"))
    frames = []
    for k in range(12):
        frame = np.full((360, 640, 3), 90, np.uint8)
        frame[60:60 + photo.shape[0], 120 + 4 * k:120 + 4 * k + photo.shape[1]] = photo
        frames.append(frame)
    root = tmp_path_factory.mktemp("window") / "take"
    make_take(root, {"c0": frames})
    return root


def test_tracking_through_windows_finds_what_whole_frames_give(moving_hand: Path, monkeypatch) -> None:
    if installed_manifest("mediapipe-hand") is None:
        pytest.fail("the MediaPipe hand model is not installed: `make test` installs it")
    take, detector = Take(moving_hand), hand_keypoint_detector("mediapipe-hand", device="cpu", threads=1)
    kp, used = _empty(12)
    track_frames(detector, take.iter_frames("c0"), 0.5, kp, used)          # whole decoded frames
    windows = []
    decode = jpeg_window.decode_window

    def counted(packet, x, y, w, h, out):
        windows.append(w * h / (out.shape[0] * out.shape[1]))
        return decode(packet, x, y, w, h, out)

    monkeypatch.setattr(jpeg_window, "decode_window", counted)
    found = detect_take(take, detector)["c0"]                              # encoded frames, windows
    assert np.isfinite(kp[:, :, :2]).all() and (kp[:, 0, 2] > 0.5).all()  # the hand in every frame
    assert len(windows) >= 10 and max(windows) < 0.5                        # tracked through windows
    np.testing.assert_array_equal(found.keypoints, kp.astype(np.float32))
