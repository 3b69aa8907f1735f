"""The read-only take reader (dataset_tools.take) on small take folders built here in DESIGN's format."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
import simplejpeg

from dataset_tools.keypoints.keypoints2d import detect_take
from manus_core.errors import TakeError
from manus_core.take import Take

FPS = 120


def make_take(root: Path, cams: dict[str, list[np.ndarray]], quality: int = 95) -> dict[str, list[bytes]]:
    """Write a take folder: take.json, frames.csv, cams/CAM.mkv (MJPEG muxed without re-encoding).

    Returns the JPEG bytes of every frame, per camera, as they went into the videos.
    """
    (root / "cams").mkdir(parents=True)
    rows, jpegs = [], {}
    for c, (cam, frames) in enumerate(cams.items()):
        tmp = root / f".jpeg_{cam}"
        tmp.mkdir()
        jpegs[cam] = []
        for k, frame in enumerate(frames):
            ok, buf = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, quality])
            assert ok
            jpegs[cam].append(buf.tobytes())
            (tmp / f"{k:06d}.jpg").write_bytes(buf.tobytes())
            t = 1_000_000_000 + round(k * 1e9 / FPS) + 137 * c
            rows.append(f"{cam},{k + 10},{t + 5_000_000},{t},{buf.size},0")
        subprocess.run(["ffmpeg", "-v", "error", "-y", "-f", "image2", "-framerate", str(FPS),
                        "-i", str(tmp / "%06d.jpg"), "-c:v", "copy", str(root / "cams" / f"{cam}.mkv")],
                       check=True)
        shutil.rmtree(tmp)
    (root / "frames.csv").write_text("cam,seq,t_device_ns,t_host_ns,bytes,flags\n" + "\n".join(rows) + "\n")
    first = next(iter(cams.values()))[0]
    (root / "take.json").write_text(json.dumps({
        "kind": "grasp", "cameras": list(cams), "fps": FPS,
        "resolution": [first.shape[1], first.shape[0]], "sync": "free-run",
        "start_ns": 1_000_000_000, "stop_ns": 2_000_000_000, "status": "complete", "leds": []}))
    return jpegs


def _frames(n: int, h: int = 48, w: int = 64, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.integers(0, 256, (h, w, 3), dtype=np.uint8), (0, 0), 3)
    out = []
    for k in range(n):
        f = base.copy()
        cv2.putText(f, str(k), (8, 36), cv2.FONT_HERSHEY_SIMPLEX, 1.0, (255, 255, 255), 2)
        out.append(f)
    return out


@pytest.fixture()
def take(tmp_path: Path) -> tuple[Path, dict[str, list[bytes]]]:
    jpegs = make_take(tmp_path / "take", {"cam00": _frames(7), "cam01": _frames(5, 40, 56, seed=1)})
    return tmp_path / "take", jpegs


def test_cameras_and_frames_csv(take) -> None:
    path, jpegs = take
    t = Take(path)
    assert t.cameras == ("cam00", "cam01")
    assert t.fps == FPS
    f = t.frames
    assert len(f["cam"]) == 12 and f["seq"].dtype == np.int64 and f["t_host_ns"].dtype == np.int64
    mine = t.camera_frames("cam01")
    assert np.array_equal(mine["seq"], np.arange(5) + 10)
    assert np.array_equal(mine["bytes"], [len(b) for b in jpegs["cam01"]])
    assert t.frame_count("cam00") == 7 and t.frame_count("cam01") == 5


def test_frames_decode_to_the_recorded_jpegs(take) -> None:
    path, jpegs = take
    t = Take(path)
    for cam in t.cameras:
        frames = dict(t.iter_frames(cam))
        assert sorted(frames) == list(range(len(jpegs[cam])))
        for k, image in frames.items():
            expected = cv2.imdecode(np.frombuffer(jpegs[cam][k], np.uint8), cv2.IMREAD_COLOR)
            assert np.array_equal(image, expected), (cam, k)
    # Packets are the muxed JPEG bytes unchanged (no re-encoding anywhere).
    assert [p.tobytes() for p in t.packets("cam00")] == jpegs["cam00"]
    stepped = [k for k, _ in t.iter_frames("cam00", start=1, step=3)]
    assert stepped == [1, 4]
    direct = t.read_frame("cam00", 5)
    assert np.array_equal(direct, cv2.imdecode(np.frombuffer(jpegs["cam00"][5], np.uint8), cv2.IMREAD_COLOR))


def test_a_frame_with_a_corrupt_scan_decodes_as_opencv_decodes_it(take) -> None:
    """simplejpeg refuses a scan that libjpeg decodes with a warning; the reader falls back to OpenCV,
    so a bit error on a camera's link costs no frame."""
    path, jpegs = take
    good = jpegs["cam00"][3]
    start = good.index(b"\xff\xda") + 16                    # inside the scan data
    bad = next(b for i in range(start, len(good) - 4) for b in (good[:i] + b"\x00\xff\x00" + good[i + 3:],)
               if _refused(b) and cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_COLOR) is not None)
    video = path / "cams" / "cam00.mkv"
    data = video.read_bytes()
    assert data.count(good) == 1
    video.write_bytes(data.replace(good, bad))
    image = Take(path).read_frame("cam00", 3)
    assert np.array_equal(image, cv2.imdecode(np.frombuffer(bad, np.uint8), cv2.IMREAD_COLOR))


def _refused(jpeg: bytes) -> bool:
    try:
        simplejpeg.decode_jpeg(jpeg, colorspace="BGR")
    except ValueError:
        return True
    return False


def test_errors_name_the_file(take, tmp_path: Path) -> None:
    path, _ = take
    with pytest.raises(TakeError, match="take.json: missing"):
        Take(tmp_path)
    with pytest.raises(TakeError, match="no camera 'cam09'"):
        Take(path).frame_count("cam09")
    with pytest.raises(TakeError, match=r"frames.csv: camera cam00 has no frame 7 \(7 frames\)"):
        Take(path).read_frame("cam00", 7)

    (path / "cams" / "cam01.mkv").rename(path / "cam01.mkv.bak")
    with pytest.raises(TakeError, match=r"cams/cam01\.mkv: missing"):
        Take(path).read_frame("cam01", 0)
    (path / "cams" / "cam01.mkv").write_bytes(b"\x1aE\xdf\xa3 this is not a video" * 10)
    with pytest.raises(TakeError, match=r"cam01\.mkv: not a Matroska file"):
        Take(path).read_frame("cam01", 0)

    # A video with fewer frames than frames.csv says (an interrupted write).
    (path / "cam01.mkv.bak").rename(path / "cams" / "cam01.mkv")
    csv = (path / "frames.csv").read_text()
    (path / "frames.csv").write_text(csv + "cam01,15,1,1,100,0\n")
    with pytest.raises(TakeError, match=r"cam01\.mkv: has 5 frames, frames.csv .* needs 6"):
        list(Take(path).iter_frames("cam01"))

    (path / "frames.csv").write_text(csv.replace("cam00,12,", "cam00,x12,"))
    with pytest.raises(TakeError, match=r"frames.csv: line 4: seq is not an integer"):
        Take(path).frames
    (path / "frames.csv").write_text(csv.replace("t_host_ns,", "t_hst_ns,"))
    with pytest.raises(TakeError, match=r"frames.csv: missing column\(s\) t_host_ns"):
        Take(path).frames
    (path / "take.json").write_text("{not json")
    with pytest.raises(TakeError, match="take.json: not valid JSON"):
        Take(path)


class _BoxDetector:
    """A stand-in for the keypoint detector: every joint at the centre of its box, confidence 1."""

    def detect_many(self, images, boxes, angles):
        return [np.tile(np.r_[(b[0, :2] + b[0, 2:]) / 2, 1.0], (1, 21, 1)) for b in boxes]


def test_detect_take_reports_frames_through_the_progress_protocol(take) -> None:
    path, _ = take
    t = Take(path)
    boxes = {cam: np.tile([0.0, 0.0, 8.0, 4.0, np.nan], (t.frame_count(cam), 1)) for cam in t.cameras}
    calls = []
    result = detect_take(t, _BoxDetector(), boxes, chunk=3, progress=lambda *call: calls.append(call))
    # 7 frames of cam00 and 5 of cam01, three at a time per camera
    assert calls == [("detect", done, 12) for done in (0, 3, 6, 7, 10, 12)]
    assert result["cam01"].keypoints.shape == (5, 21, 3) and np.all(result["cam00"].keypoints[:, :, :2] == [4, 2])
