"""The recorder's pipeline (rig.record.streams): readers hand frames to their writers through rings
without waking them; writers batch, raw frames are encoded on several threads at once, a full
ring and a camera that hangs are accounted for."""

from __future__ import annotations

import dataclasses
import threading
import time

import cv2
import numpy as np
from test_recorder_raw import RawCamera

import rig.record.recorder as recorder_module
from manus_core.take import Take
from rig.cameras import CameraInfo, Frame, TakeCameras
from rig.clock import MonotonicClock, VirtualClock
from rig.layouts import make_rig
from rig.mkv import MkvWriter
from rig.record import FLAG_HOST_JPEG, Recorder, streams

W, H = 160, 96


def small_jpeg(seed: int = 0) -> bytes:
    image = cv2.GaussianBlur(np.random.default_rng(seed).integers(0, 256, (H, W, 3), dtype=np.uint8), (0, 0), 2)
    return cv2.imencode(".jpg", image)[1].tobytes()


class PacedCamera:
    """A UVC-like camera on CLOCK_MONOTONIC: a frame every 1/fps s; `hang_after` frames, read()
    blocks until `release` is set (a driver that stopped answering); `handed` counts the frames
    read() returned."""

    def __init__(self, cam_id: str, fps: float, data: bytes, hang_after: int | None = None) -> None:
        self.id, self.period, self.data, self.hang_after = cam_id, 1e9 / fps, data, hang_after
        self.t0, self.handed = 0, 0
        self.release = threading.Event()

    def open(self) -> None: ...

    def configure(self) -> None: ...

    def start(self) -> None:
        self.t0 = time.monotonic_ns() + 5_000_000

    def stop(self) -> None:
        self.release.set()

    def close(self) -> None: ...

    def trigger(self) -> None: ...

    def info(self) -> CameraInfo:
        return CameraInfo(self.id, "test", "paced", self.id, W, H, 1e9 / self.period, "MJPG")

    def read(self, timeout_s: float = 1.0) -> Frame | None:
        if self.hang_after is not None and self.handed >= self.hang_after:
            self.release.wait()
            return None
        ready = self.t0 + self.handed * self.period
        wait = (ready - time.monotonic_ns()) / 1e9
        if wait > timeout_s:
            time.sleep(timeout_s)
            return None
        time.sleep(max(0.0, wait))
        k = self.handed
        self.handed += 1
        return Frame(self.data, k, int(ready), time.monotonic_ns(), W, H, "jpeg")


def rig_of(cameras: int, fps: float = 120.0):
    return make_rig("cube53", cameras=cameras, resolution=(W, H), fps=fps, backend="v4l2", seed=2)


def test_writers_store_every_frame_in_batches(tmp_path, monkeypatch):
    """8 cameras at 120 FPS in real time: every frame read is stored, in order, and a writer stores
    several frames per system call (it is not woken per frame)."""
    calls = []
    write = MkvWriter.write

    def counting_write(self, jpegs):
        calls.append(len(jpegs))
        write(self, jpegs)

    monkeypatch.setattr(MkvWriter, "write", counting_write)
    rig = rig_of(8)
    data = small_jpeg()
    cams = {c.id: PacedCamera(c.id, c.fps, data) for c in rig.cameras}
    result = Recorder(rig, tmp_path / "t", "calibration", 0.5, TakeCameras(cams), MonotonicClock()).run()
    assert result.status == "complete"
    take = Take(tmp_path / "t")
    for report in result.cameras:
        rows = take.camera_frames(report.id)
        # nothing lost: every frame read is stored, in order
        assert report.seq_gaps == report.overflows == 0
        assert rows["seq"].tolist() == list(range(rows["seq"][0], rows["seq"][0] + len(rows["seq"])))
        assert report.frames == len(rows["seq"]) == cams[report.id].handed - rows["seq"][0]
        assert len(list(take.packets(report.id))) == report.frames
    assert sum(calls) == result.frames
    assert result.frames / len(calls) >= 1.5, calls   # PASS_S of 120 FPS frames per call: 2 to 3


def test_a_full_ring_counts_its_overflows(tmp_path, monkeypatch):
    """A writer that falls behind (a disk that stalls) fills a camera's ring: the frames that do not
    fit are counted as overflows, never stall the reader, and every frame read is either stored or
    counted."""
    monkeypatch.setattr(recorder_module, "RING_S", 0.0)   # the smallest ring: 8 frames
    store = streams.Stream._store

    def stalling_store(self, frames):
        time.sleep(0.15)
        store(self, frames)

    monkeypatch.setattr(streams.Stream, "_store", stalling_store)
    rig = rig_of(1)
    cid = rig.cameras[0].id
    cam = PacedCamera(cid, 120, small_jpeg())
    result = Recorder(rig, tmp_path / "t", "calibration", 0.6, TakeCameras({cid: cam}), MonotonicClock()).run()
    report = result.cameras[0]
    assert result.status == "complete" and report.overflows > 10
    first = Take(tmp_path / "t").camera_frames(cid)["seq"][0]
    assert report.frames + report.overflows == cam.handed - first
    assert report.seq_gaps <= report.overflows   # what the host lost, as gaps where later frames were stored


def test_a_camera_whose_read_never_returns_is_abandoned(tmp_path, monkeypatch):
    """A hung driver and a stop (Ctrl-C): the take still ends, the hung camera's frames so far are
    stored and its file is finished, the other cameras record up to the stop."""
    monkeypatch.setattr(recorder_module, "JOIN_S", 0.3)
    rig = rig_of(3)
    data = small_jpeg()
    hung = rig.cameras[1].id
    cams = {c.id: PacedCamera(c.id, c.fps, data, hang_after=12 if c.id == hung else None) for c in rig.cameras}
    rec = Recorder(rig, tmp_path / "t", "calibration", 5.0, TakeCameras(cams), MonotonicClock())
    stop = threading.Timer(0.6, rec.stop.set, args=("stopped by the test",))
    stop.start()
    result = rec.run()
    reports = {r.id: r for r in result.cameras}
    assert result.status == "interrupted" and result.reason == "stopped by the test"
    assert reports[hung].status == "failed" and "did not return" in reports[hung].error
    take = Take(tmp_path / "t")
    assert reports[hung].frames == len(list(take.packets(hung))) == 12
    for cid, report in reports.items():
        if cid != hung:
            assert report.status == "ok" and report.frames >= 40 and report.seq_gaps == 0


def test_raw_frames_are_encoded_on_several_threads_and_decode_to_the_raw_pixels(tmp_path, monkeypatch):
    """Raw frames of 4 cameras: each camera's writer encodes its frames (the encoding is spread
    over threads, which OpenCV lets run at once), and every stored JPEG decodes to the camera's
    pixels within JPEG's tolerance."""
    rng = np.random.default_rng(7)
    gray = cv2.GaussianBlur(rng.integers(0, 256, (H, W), dtype=np.uint8), (0, 0), 2)
    yy, xx = np.mgrid[0:H, 0:W]
    bgr = np.stack([xx * 255 // W, np.full_like(xx, 128), 40 + yy * 200 // H], -1).astype(np.uint8)
    mosaic = np.empty((H, W), np.uint8)   # RGGB
    mosaic[0::2, 0::2], mosaic[0::2, 1::2] = bgr[0::2, 0::2, 2], bgr[0::2, 1::2, 1]
    mosaic[1::2, 0::2], mosaic[1::2, 1::2] = bgr[1::2, 0::2, 1], bgr[1::2, 1::2, 0]
    threads: dict[str, set[str]] = {}
    encode = streams.frame_jpeg

    def watched(frame, params):
        data, flags = encode(frame, params)
        threads.setdefault(threading.current_thread().name, set()).add(frame.encoding)
        return data, flags

    monkeypatch.setattr(streams, "frame_jpeg", watched)
    rig = make_rig("cube53", cameras=4, resolution=(W, H), backend="aravis", seed=1)
    rig = dataclasses.replace(rig, storage=dataclasses.replace(rig.storage, jpeg_quality=95))
    clock = VirtualClock(time_scale=0)
    t0 = clock.now_ns() + 1_000_000
    ids = [c.id for c in rig.cameras]
    cams = {cid: RawCamera(cid, gray if i % 2 == 0 else mosaic, "mono8" if i % 2 == 0 else "bayer_rg8", clock, t0)
            for i, cid in enumerate(ids)}
    result = Recorder(rig, tmp_path / "t", "calibration", 0.2, TakeCameras(cams, t0_ns=t0), clock).run()
    assert result.status == "complete"
    assert [(r.frames, r.seq_gaps, r.overflows) for r in result.cameras] == [(25, 0, 0)] * 4
    assert sorted(threads) == sorted(f"write-{cid}" for cid in ids)
    take = Take(tmp_path / "t")
    assert np.all(take.frames["flags"].astype(int) == FLAG_HOST_JPEG)
    inner = (slice(4, -4), slice(4, -4))   # demosaicing is approximate at the borders
    for i, cid in enumerate(ids):
        image = take.read_frame(cid, 10).astype(int)
        if i % 2 == 0:
            assert np.abs(image[..., 0] - gray).mean() < 2
        else:
            assert np.abs(image[inner] - bgr[inner]).mean() < 4
