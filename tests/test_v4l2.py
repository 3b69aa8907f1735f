"""The V4L2 backend above its thin device layer, fed with recorded driver buffers.

These machines have no V4L2 devices; a fake CaptureDevice replays JPEG buffers with the
driver timestamps OpenCV would report (CAP_PROP_POS_MSEC), including padded buffers, torn
frames, missing Huffman tables, lost frames and a camera that is unplugged.
"""

from __future__ import annotations

import os
import time

import cv2
import numpy as np
import pytest

from manus_core.errors import CameraDisconnected, CameraError
from manus_core.rig_config import CameraConfig
from rig.cameras import Camera
from rig.cameras.mjpeg import STANDARD_DHT, jpeg_header, jpeg_trim
from rig.cameras.v4l2 import TimestampSequencer, V4l2Camera, buffer_time_to_monotonic_ns, fourcc_code, list_v4l2_cameras

W, H, FPS = 64, 48, 120.0


class RecordedCapture:
    """A CaptureDevice replaying (buffer, pos_msec) pairs; it negotiates what it is told to."""

    def __init__(self, path, buffers, offer=None):
        self.path = str(path)
        self.buffers = list(buffers)
        self.calls: list[tuple[str, float]] = []
        self.values: dict[str, float] = {}
        self.offer = offer or {}
        self.released = False

    def open(self):
        return os.path.exists(self.path)

    def set(self, name, value):
        self.calls.append((name, value))
        self.values[name] = self.offer.get(name, value)
        return True

    def get(self, name):
        return float(self.values.get(name, 0.0))

    def grab(self):
        return self.buffers.pop(0) if self.buffers else None

    def release(self):
        self.released = True


def _image(k: int) -> np.ndarray:
    """A frame whose content says which frame it is (a bar that moves one column per frame)."""
    img = np.full((H, W, 3), 40, np.uint8)
    img[:, (k * 3) % W:(k * 3) % W + 6] = (30, 200, 90)
    return img


def _jpeg(k: int) -> bytes:
    return cv2.imencode(".jpg", _image(k), [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()


def _strip_huffman(jpeg: bytes) -> bytes:
    out, pos = bytearray(jpeg[:2]), 2
    while jpeg[pos + 1] != 0xDA:
        length = int.from_bytes(jpeg[pos + 2:pos + 4], "big")
        if jpeg[pos + 1] != 0xC4:
            out += jpeg[pos:pos + 2 + length]
        pos += 2 + length
    return bytes(out + jpeg[pos:])


@pytest.fixture()
def device_node(tmp_path):
    node = tmp_path / "usb-Cam_Model_SN42-video-index0"
    node.write_bytes(b"")
    return node


def _cfg(node, **kw) -> CameraConfig:
    return CameraConfig(id="cam07", backend="v4l2", device=str(node), width=W, height=H, fps=FPS, **kw)


def _camera(node, buffers, **offer) -> tuple[V4l2Camera, RecordedCapture]:
    dev = RecordedCapture(node, buffers, offer)
    cam = V4l2Camera(_cfg(node), device=dev)
    cam.open()
    cam.configure()
    cam.start()
    return cam, dev


def _read_all(cam):
    # the recording ends with an empty grab, which returns None at once; a short timeout would let a
    # loaded machine end the read early while the backend is still skipping rejected buffers
    frames = []
    while (f := cam.read(10.0)) is not None:
        frames.append(f)
    return frames


def test_recorded_stream_numbering_drops_and_repairs(device_node):
    """Every delivered frame keeps its true index across losses and the frames the backend
    rejects; padding is trimmed, missing tables are added, timestamps pass through."""
    rng = np.random.default_rng(3)
    base_ms = time.clock_gettime_ns(time.CLOCK_MONOTONIC) / 1e6
    n = 240
    stamps = base_ms + np.arange(n) * (1000 / FPS) + rng.uniform(-0.8, 0.8, n)   # ±0.8 ms jitter
    lost = {5, 6, 50, 51, 52, 131}                    # never reached the host
    torn, wrong_size, padded, no_tables = {20, 200}, {77}, {3, 90, 91}, {10, 11, 150}
    buffers, expected = [], []
    for k in range(n):
        if k in lost:
            continue
        data = _jpeg(k)
        if k in torn:
            data = data[: len(data) // 2]            # cut mid-scan: no EOI
        if k in wrong_size:
            data = cv2.imencode(".jpg", np.zeros((H * 2, W * 2, 3), np.uint8))[1].tobytes()
        if k in no_tables:
            data = _strip_huffman(data)
        if k in padded:
            data = data + bytes(512)                 # the driver's buffer is larger than the JPEG
        buffers.append((data, float(stamps[k])))
        if k not in torn | wrong_size:
            expected.append(k)
    buffers.insert(30, buffers[29])                  # a buffer handed out twice
    cam, _ = _camera(device_node, buffers)
    frames = _read_all(cam)

    assert [f.seq for f in frames] == expected
    stats = cam.stats()
    assert stats["lost"] == n - len(expected)
    assert (stats["corrupt"], stats["size_mismatch"], stats["repeated"], stats["tables_added"]) == (2, 1, 1, 3)
    assert stats["period_ms"] == pytest.approx(1000 / FPS, rel=2e-3)
    for f in frames:
        assert f.data.startswith(b"\xff\xd8") and f.data.endswith(b"\xff\xd9")
        decoded = cv2.imdecode(np.frombuffer(f.data, np.uint8), cv2.IMREAD_COLOR)
        reference = cv2.imdecode(np.frombuffer(_jpeg(f.seq), np.uint8), cv2.IMREAD_COLOR)
        assert np.array_equal(decoded, reference)
        assert abs(f.t_device_ns - stamps[f.seq] * 1e6) < 1_000          # µs: double ms precision
        assert (f.width, f.height, f.encoding) == (W, H, "jpeg")


def test_inserted_tables_are_the_ones_the_encoder_uses():
    """The Annex K tables inserted into table-less MJPEG equal libjpeg's default tables."""
    jpeg = _jpeg(0)
    segments, pos = [], 2
    while jpeg[pos + 1] != 0xDA:
        length = int.from_bytes(jpeg[pos + 2:pos + 4], "big")
        if jpeg[pos + 1] == 0xC4:
            segments.append(jpeg[pos + 4:pos + 2 + length])
        pos += 2 + length
    body, tables = STANDARD_DHT[4:], []
    while body:
        size = 17 + sum(body[1:17])
        tables.append(body[:size])
        body = body[size:]
    assert sorted(segments) == sorted(tables) and len(tables) == 4
    header = jpeg_header(_strip_huffman(jpeg))
    assert header is not None and not header.has_huffman and (header.width, header.height) == (W, H)


def test_camera_running_off_nominal_rate_has_no_false_drops():
    """A "120 FPS" camera at 119.88 FPS: the tracked period absorbs the 0.1 % difference."""
    seq = TimestampSequencer(120.0)
    t = np.round(np.arange(3000) * 1e9 / 119.88).astype(np.int64)
    out = [seq(int(x)) for x in np.delete(t, [1000, 2000, 2001])]
    assert seq.lost == 3
    assert out[-1] == 2999
    assert seq.period_ns == pytest.approx(1e9 / 119.88, rel=1e-4)


def test_buffer_timestamps_on_either_clock():
    mono, real = 5_000_000_000_000, 1_790_000_000_000_000_000
    assert buffer_time_to_monotonic_ns((mono - 3_000_000) / 1e6, mono, real) == mono - 3_000_000
    # A driver that stamps wall time: moved onto the monotonic clock.
    got = buffer_time_to_monotonic_ns((real - 3_000_000) / 1e6, mono, real)
    assert abs(got - (mono - 3_000_000)) < 1_000_000      # double ms at 1.8e12 ms: sub-ms precision
    assert buffer_time_to_monotonic_ns(0.0, mono, real) is None


def test_missing_driver_timestamps_fall_back_to_arrival(device_node):
    cam, _ = _camera(device_node, [(_jpeg(0), 0.0), (_jpeg(1), 0.0)])
    frames = _read_all(cam)
    assert len(frames) == 2 and cam.stats()["no_timestamp"] == 2
    assert all(f.t_device_ns == f.t_host_ns for f in frames)


def test_configure_asks_for_mjpeg_passthrough(device_node):
    cam, dev = _camera(device_node, [])
    names = [name for name, _ in dev.calls]
    assert names.index("fourcc") < names.index("width") < names.index("height")
    calls = dict(dev.calls)
    assert calls["fourcc"] == fourcc_code("MJPG") == cv2.VideoWriter_fourcc(*"MJPG")
    assert calls["convert_rgb"] == 0 and calls["buffersize"] == 4 and calls["fps"] == FPS
    assert calls["auto_exposure"] == 1 and calls["exposure"] == pytest.approx(20.0)   # 2000 µs
    assert cam.info().pixel_format == "MJPG" and cam.info().serial == "SN42"
    assert isinstance(cam, Camera)


@pytest.mark.parametrize("offer, message", [
    ({"width": 640, "height": 480}, "asked for 64x48 MJPG, the device gave 640x480 MJPG"),
    ({"fourcc": fourcc_code("YUYV")}, "the device gave 64x48 YUYV"),
    ({"fps": 30.0}, "asked for 120 FPS at 64x48, the device offers 30"),
])
def test_configure_refuses_what_the_device_did_not_give(device_node, offer, message):
    dev = RecordedCapture(device_node, [], offer)
    cam = V4l2Camera(_cfg(device_node), device=dev)
    cam.open()
    with pytest.raises(CameraError, match=message):
        cam.configure()


def test_unplugged_camera_is_reported_and_timeouts_are_not(device_node):
    cam, dev = _camera(device_node, [(_jpeg(0), 1000.0)])
    assert cam.read(0.05).seq == 0
    assert cam.read(0.05) is None and cam.stats()["timeouts"] == 1
    device_node.unlink()
    with pytest.raises(CameraDisconnected, match="cam07"):
        cam.read(0.05)
    cam.close()
    assert dev.released


def test_triggered_sync_is_refused(device_node):
    with pytest.raises(CameraError, match="cannot be triggered"):
        V4l2Camera(_cfg(device_node), sync="software-trigger", device=RecordedCapture(device_node, []))


def test_jpeg_trim_rejects_non_jpeg():
    assert jpeg_trim(b"\x00\x00\xff\xd9") is None
    assert jpeg_trim(b"\xff\xd8\x01\x02") is None


def test_discovery_lists_capture_nodes_by_id(tmp_path):
    by_id, sysfs, dev = tmp_path / "by-id", tmp_path / "sys", tmp_path / "dev"
    for d in (by_id, dev):
        d.mkdir()
    for node, name, model in [("video0", "usb-046d_HD_Pro_Webcam_C920_AB12CD-video-index0", "HD Pro Webcam C920"),
                              ("video1", "usb-046d_HD_Pro_Webcam_C920_AB12CD-video-index1", None),
                              ("video2", "usb-Arducam_OV9281_USB_Camera_UC762-video-index0", "Arducam OV9281")]:
        (dev / node).write_bytes(b"")
        (by_id / name).symlink_to(dev / node)
        if model:
            (sysfs / node).mkdir(parents=True)
            (sysfs / node / "name").write_text(model + "\n")
    found = list_v4l2_cameras(by_id, sysfs)
    assert [(c.device.rsplit("/", 1)[1], c.model, c.serial, c.address.rsplit("/", 1)[1]) for c in found] == [
        ("usb-046d_HD_Pro_Webcam_C920_AB12CD-video-index0", "HD Pro Webcam C920", "AB12CD", "video0"),
        ("usb-Arducam_OV9281_USB_Camera_UC762-video-index0", "Arducam OV9281", "UC762", "video2")]
    assert list_v4l2_cameras(tmp_path / "missing", sysfs) == []
