"""Raw machine-vision frames through the recorder: JPEG encoding, stored chroma, a registered
backend, a virtual clock's back-pressure and Aravis's own Fake camera."""

from __future__ import annotations

import dataclasses
import time

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from test_recorder import PERIOD_NS, check_readable, wrap_backend

import rig.record.streams as streams
from manus_capture.cli import cli
from manus_core.errors import RecordError
from manus_core.take import Take
from rig.backends import BACKENDS
from rig.cameras import Backend, CameraInfo, FoundCamera, Frame, TakeCameras
from rig.cameras.aravis import aravis
from rig.clock import VirtualClock
from rig.layouts import make_rig
from rig.record import FLAG_HOST_JPEG, Recorder, RecordOptions, record_take


class RawCamera:
    """A machine-vision camera handing out raw pixels on a virtual clock."""

    def __init__(self, cam_id: str, image: np.ndarray, encoding: str, clock: VirtualClock, t0: int) -> None:
        self.id, self.image, self.encoding, self.clock, self.t0, self.k = cam_id, image, encoding, clock, t0, 0

    def open(self) -> None: ...

    def configure(self) -> None: ...

    def start(self) -> None: ...

    def stop(self) -> None: ...

    def close(self) -> None: ...

    def trigger(self) -> None: ...

    def info(self) -> CameraInfo:
        h, w = self.image.shape[:2]
        return CameraInfo(self.id, "aravis", "raw", "0", w, h, 120.0, self.encoding)

    def read(self, timeout_s: float = 1.0) -> Frame:
        t = self.t0 + int(self.k * PERIOD_NS)
        self.clock.advance_to(t)
        self.k += 1
        h, w = self.image.shape[:2]
        return Frame(self.image.tobytes(), self.k - 1, t, t, w, h, self.encoding)


def test_raw_frames_are_jpeg_encoded(tmp_path):
    rig = make_rig("cube53", cameras=2, resolution=(64, 48), backend="aravis", seed=1)
    rng = np.random.default_rng(0)
    gray = cv2.GaussianBlur(rng.integers(0, 256, (48, 64), dtype=np.uint8), (0, 0), 2)
    yy, xx = np.mgrid[0:48, 0:64]
    bgr = np.stack([xx * 4, np.full_like(xx, 128), 40 + yy * 4], -1).astype(np.uint8)  # blue ramp across, red down
    bayer = np.zeros((48, 64), np.uint8)   # RGGB mosaic of `bgr`
    bayer[0::2, 0::2], bayer[0::2, 1::2] = bgr[0::2, 0::2, 2], bgr[0::2, 1::2, 1]
    bayer[1::2, 0::2], bayer[1::2, 1::2] = bgr[1::2, 0::2, 1], bgr[1::2, 1::2, 0]
    clock = VirtualClock(time_scale=0)
    t0 = clock.now_ns() + 1_000_000
    ids = [c.id for c in rig.cameras]
    cams = {ids[0]: RawCamera(ids[0], gray, "mono8", clock, t0),
            ids[1]: RawCamera(ids[1], bayer, "bayer_rg8", clock, t0)}
    result = Recorder(rig, tmp_path / "t", "calibration", 0.05, TakeCameras(cams, t0_ns=t0), clock).run()
    assert result.status == "complete"
    take = Take(tmp_path / "t")
    assert check_readable(tmp_path / "t") == {ids[0]: 7, ids[1]: 7}
    assert np.all(take.frames["flags"].astype(int) == FLAG_HOST_JPEG)
    mono = take.read_frame(ids[0], 3)
    assert np.abs(mono[..., 0].astype(int) - gray).mean() < 3
    colour = take.read_frame(ids[1], 3).astype(int)
    inner = (slice(4, -4), slice(4, -4))   # demosaicing is approximate at the borders
    assert np.abs(colour[inner] - bgr[inner]).mean() < 4
    assert np.abs(colour[inner] - bgr[inner][..., ::-1]).mean() > 40   # red and blue in their places


def test_a_registered_backend_records_and_is_listed(tmp_path, monkeypatch):
    """A backend is one registry entry: record_take opens its cameras on its clock, `rig list` asks it."""
    image = np.full((48, 64), 128, np.uint8)

    def open_take(setup):
        t0 = setup.clock.now_ns() + 1_000_000
        cams = {c.id: RawCamera(c.id, image, "mono8", setup.clock, t0) for c in setup.cameras}
        return TakeCameras(cams, t0_ns=t0, note="fake raw cameras")

    found = FoundCamera("fake", "fake:0", model="Raw")
    monkeypatch.setitem(BACKENDS, "fake", Backend("fake", open_take, discover=lambda fake: [found],
                                                  clock=lambda rig: VirtualClock(time_scale=0)))
    rig = make_rig("cube53", cameras=2, resolution=(64, 48), backend="aravis", seed=1)
    rig = dataclasses.replace(rig, cameras=tuple(dataclasses.replace(c, backend="fake") for c in rig.cameras))
    result = record_take(rig, tmp_path / "s", "t", "calibration", 0.05, RecordOptions(use_leds=False))
    assert result.status == "complete" and result.meta["backend_note"] == "fake raw cameras"
    assert check_readable(tmp_path / "s" / "t") == {c.id: 7 for c in rig.cameras}
    listed = CliRunner().invoke(cli, ["rig", "list", "--no-aravis"])
    assert listed.exit_code == 0 and "fake    fake:0  (model Raw)" in listed.output
    # a backend on a clock of its own cannot share a take with the host's cameras
    mixed = dataclasses.replace(rig, cameras=(rig.cameras[0], dataclasses.replace(rig.cameras[1], backend="v4l2")))
    with pytest.raises(RecordError, match="simulated and real cameras cannot share a take"):
        record_take(mixed, tmp_path / "s", "u", "calibration", 0.05, RecordOptions(use_leds=False))


def test_a_fast_virtual_clock_never_overflows_a_slow_writer(tmp_path, monkeypatch):
    """A simulated camera on a fast clock outruns any disk; it has no real time to keep, so its reader
    waits for the writer instead of losing frames (a loaded CI machine lost some before)."""
    store = streams.Stream._store

    def slow_store(self, frames):
        time.sleep(0.02)
        store(self, frames)

    monkeypatch.setattr(streams.Stream, "_store", slow_store)
    rig = make_rig("cube53", cameras=1, resolution=(64, 48), backend="aravis", seed=1)
    clock = VirtualClock(time_scale=0)
    t0 = clock.now_ns() + 1_000_000
    cid = rig.cameras[0].id
    image = np.full((48, 64), 128, np.uint8)
    # 1 s at 120 FPS is 121 frames against a ring of 60: without the wait half of them were lost
    result = Recorder(rig, tmp_path / "t", "calibration", 1.0,
                      TakeCameras({cid: RawCamera(cid, image, "mono8", clock, t0)}, t0_ns=t0), clock).run()
    assert result.status == "complete"
    assert [(r.frames, r.overflows, r.seq_gaps) for r in result.cameras] == [(121, 0, 0)]
    assert check_readable(tmp_path / "t") == {cid: 121}


@pytest.mark.parametrize("chroma", ["444", "420"])
def test_stored_jpeg_chroma(tmp_path, chroma):
    rig = make_rig("cube53", cameras=1, resolution=(64, 48), backend="aravis", seed=1)
    rig = dataclasses.replace(rig, storage=dataclasses.replace(rig.storage, jpeg_chroma=chroma))
    stripes = np.zeros((48, 64, 3), np.uint8)   # one-pixel columns: red, green, red, ...
    stripes[:, 0::2, 2] = 220
    stripes[:, 1::2, 1] = 200
    clock = VirtualClock(time_scale=0)
    t0 = clock.now_ns() + 1_000_000
    cid = rig.cameras[0].id
    result = Recorder(rig, tmp_path / "t", "calibration", 0.03,
                      TakeCameras({cid: RawCamera(cid, stripes, "bgr8", clock, t0)}, t0_ns=t0), clock).run()
    assert result.status == "complete"
    take = Take(tmp_path / "t")
    assert take.meta["storage"] == {"jpeg_quality": 90, "jpeg_chroma": chroma}
    error = np.abs(take.read_frame(cid, 1).astype(int) - stripes).mean()
    # full-resolution colour keeps each column's hue; 4:2:0 averages neighbouring columns to yellow
    assert error < 15 if chroma == "444" else error > 40, error


def test_aravis_fake_camera_records_through_the_same_path(tmp_path, monkeypatch):
    """Aravis's in-process Fake camera (mono8, real time): raw frames are JPEG-encoded as they come."""
    try:
        aravis().enable_interface("Fake")
    except Exception as exc:   # CameraError without Aravis, GLib errors without the Fake interface
        pytest.skip(f"Aravis 0.8 Fake interface not available ({exc})")
    rig = make_rig("cube53", cameras=1, resolution=(64, 48), fps=100.0, backend="aravis")
    cam = dataclasses.replace(rig.cameras[0], device="Fake_1", exposure_us=8000.0, gain_db=0.0)  # a visible ramp
    rig = dataclasses.replace(rig, cameras=(cam,))
    raw: list[Frame] = []

    class Keep:
        def __init__(self, inner):
            self.inner = inner

        def read(self, timeout_s: float = 1.0):
            frame = self.inner.read(timeout_s)
            if frame is not None:
                raw.append(frame)
            return frame

        def __getattr__(self, name):
            return getattr(self.inner, name)

    wrap_backend(monkeypatch, "aravis", lambda cid, c: Keep(c))
    result = record_take(rig, tmp_path / "s", "t", "calibration", 0.3, RecordOptions(use_leds=False))
    assert result.status == "complete" and result.cameras[0].encoding == "mono8"
    # a real-time stream: how many frames a loaded machine reads is not the point, only that the
    # take ends on time (0.35 s at 100 FPS) and stores every frame read
    assert check_readable(tmp_path / "s" / "t") == {cam.id: len(raw)} and 6 <= len(raw) <= 45
    take = Take(tmp_path / "s" / "t")
    rows = take.camera_frames(cam.id)
    assert rows["seq"].tolist() == [f.seq for f in raw] and np.all(rows["flags"].astype(int) == FLAG_HOST_JPEG)
    image = take.read_frame(cam.id, 5)[..., 0].astype(int)
    pixels = np.frombuffer(raw[5].data, np.uint8)[:64 * 48].reshape(48, 64)
    assert pixels.std() > 10 and np.abs(image - pixels).mean() < 3
