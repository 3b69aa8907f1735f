"""UVC cameras through OpenCV's V4L2 backend, MJPEG passed through without decoding.

The device calls live in one thin class, `CvCapture` (open, set/get a property, grab one
buffer with its timestamp, release). Everything above it is plain code tested with recorded
buffers: trimming and validating each JPEG, adding the Huffman tables many UVC cameras leave
out (rig.cameras.mjpeg), moving the driver's buffer timestamp onto CLOCK_MONOTONIC, and numbering frames. OpenCV
does not expose the driver's sequence numbers, so `seq` is inferred from the buffer
timestamps: a gap of k frame periods is k-1 lost frames.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, Protocol

import cv2

from manus_core.errors import CameraDisconnected, CameraError
from manus_core.rig_config import CameraConfig

from . import Backend, CameraInfo, FoundCamera, Frame, TakeCameras, TakeSetup
from .mjpeg import jpeg_header, jpeg_trim, with_huffman_tables


# -- time and numbering -----------------------------------------------------------------------
def buffer_time_to_monotonic_ns(pos_msec: float, mono_now_ns: int, real_now_ns: int) -> int | None:
    """The driver's buffer timestamp (OpenCV's CAP_PROP_POS_MSEC) on CLOCK_MONOTONIC.

    uvcvideo stamps buffers with CLOCK_MONOTONIC; old drivers used wall time, recognised by
    being nearer the wall clock than the monotonic one. 0 (OpenCV's answer before the first
    frame) means unknown.
    """
    if not pos_msec or pos_msec <= 0:
        return None
    t = int(round(pos_msec * 1e6))
    if abs(t - real_now_ns) < abs(t - mono_now_ns):
        return t - (real_now_ns - mono_now_ns)
    return t


class TimestampSequencer:
    """Sequence numbers from buffer timestamps when the driver's own are not available.

    The step is the gap in frame periods, rounded; the period follows the camera's true rate
    (a nominal 120 FPS camera may run at 119.88) from single-period steps. A timestamp that
    does not advance is a repeated buffer and gets no number.
    """

    def __init__(self, fps: float) -> None:
        self.period_ns = 1e9 / fps
        self._last: int | None = None
        self.seq = -1
        self.lost = 0

    def __call__(self, t_ns: int) -> int | None:
        if self._last is None:
            self._last, self.seq = t_ns, 0
            return 0
        dt = t_ns - self._last
        if dt <= 0:
            return None
        step = max(1, int(round(dt / self.period_ns)))
        if step == 1:
            self.period_ns += 0.05 * (dt - self.period_ns)
        self.lost += step - 1
        self.seq += step
        self._last = t_ns
        return self.seq


# -- the thin device layer --------------------------------------------------------------------
class CaptureDevice(Protocol):
    """What V4l2Camera needs from a device; CvCapture is the real one, tests feed recordings."""

    path: str

    def open(self) -> bool: ...

    def set(self, name: str, value: float) -> bool: ...

    def get(self, name: str) -> float: ...

    def grab(self) -> tuple[bytes, float] | None: ...

    def release(self) -> None: ...


class CvCapture:
    """cv2.VideoCapture on CAP_V4L2: the only code here that talks to a device."""

    def __init__(self, path: str) -> None:
        self.path = path
        self._cap: Any = None
        self._props = {"fourcc": cv2.CAP_PROP_FOURCC, "width": cv2.CAP_PROP_FRAME_WIDTH,
                       "height": cv2.CAP_PROP_FRAME_HEIGHT, "fps": cv2.CAP_PROP_FPS,
                       "buffersize": cv2.CAP_PROP_BUFFERSIZE, "convert_rgb": cv2.CAP_PROP_CONVERT_RGB,
                       "auto_exposure": cv2.CAP_PROP_AUTO_EXPOSURE, "exposure": cv2.CAP_PROP_EXPOSURE,
                       "read_timeout_ms": cv2.CAP_PROP_READ_TIMEOUT_MSEC}

    def open(self) -> bool:
        self._cap = cv2.VideoCapture(self.path, cv2.CAP_V4L2)
        return bool(self._cap.isOpened())

    def set(self, name: str, value: float) -> bool:
        return bool(self._cap.set(self._props[name], value))

    def get(self, name: str) -> float:
        return float(self._cap.get(self._props[name]))

    def grab(self) -> tuple[bytes, float] | None:
        if not self._cap.grab():
            return None
        ok, buf = self._cap.retrieve()
        if not ok or buf is None:
            return None
        return buf.tobytes(), float(self._cap.get(cv2.CAP_PROP_POS_MSEC))

    def release(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


def fourcc_code(text: str) -> int:
    return sum(ord(c) << 8 * i for i, c in enumerate(text[:4].ljust(4)))


def fourcc_text(code: float) -> str:
    value = int(code)
    return "".join(chr((value >> 8 * i) & 0xFF) for i in range(4))


# -- the camera -------------------------------------------------------------------------------
class V4l2Camera:
    """A UVC camera behind the Camera protocol; frames are MJPEG bytes (or packed YUYV).

    UVC cameras free-run: they cannot be triggered. Exposure is set in manual mode (V4L2
    units of 100 µs); UVC gain has no unit, so gain_db is not applied.
    """

    backend = "v4l2"

    def __init__(self, cfg: CameraConfig, *, sync: str = "free-run", buffers: int = 4,
                 device: CaptureDevice | None = None) -> None:
        if sync != "free-run":
            raise CameraError(f"camera {cfg.id}: UVC cameras cannot be triggered (sync {sync!r}); "
                              "use sync = \"free-run\"")
        self.cfg = cfg
        self.buffers = buffers
        self._dev = device if device is not None else CvCapture(cfg.device)
        self._fourcc = cfg.pixel_format.upper()
        self._readback: dict[str, Any] = {}
        self._sequencer = TimestampSequencer(cfg.fps)
        self._counts = self._zero_counts()
        self._opened = False
        self._timeout_ms: int | None = None

    @staticmethod
    def _zero_counts() -> dict[str, int]:
        return {"frames": 0, "lost": 0, "corrupt": 0, "size_mismatch": 0, "repeated": 0,
                "tables_added": 0, "timeouts": 0, "no_timestamp": 0}

    def open(self) -> None:
        if not self._dev.open():
            raise CameraError(f"camera {self.cfg.id}: cannot open {self.cfg.device} with V4L2")
        self._opened = True

    def configure(self) -> None:
        cfg = self.cfg
        if self._fourcc not in ("MJPG", "YUYV"):
            raise CameraError(f"camera {cfg.id}: pixel format {cfg.pixel_format!r} is not MJPG or YUYV")
        # Format before size: a size is only valid for the format it is asked with.
        steps = [("fourcc", fourcc_code(self._fourcc)), ("width", cfg.width), ("height", cfg.height),
                 ("fps", cfg.fps), ("buffersize", self.buffers), ("convert_rgb", 0),
                 ("auto_exposure", 1), ("exposure", cfg.exposure_us / 100.0)]
        refused = [name for name, value in steps if not self._dev.set(name, value)]
        self._readback = {"fourcc": fourcc_text(self._dev.get("fourcc")), "width": int(self._dev.get("width")),
                          "height": int(self._dev.get("height")), "fps": self._dev.get("fps"),
                          "buffersize": int(self._dev.get("buffersize")),
                          "exposure_us": self._dev.get("exposure") * 100.0, "refused": refused}
        got = self._readback
        if (got["fourcc"], got["width"], got["height"]) != (self._fourcc, cfg.width, cfg.height):
            raise CameraError(f"camera {cfg.id}: asked for {cfg.width}x{cfg.height} {self._fourcc}, "
                              f"the device gave {got['width']}x{got['height']} {got['fourcc']}")
        if got["fps"] < 0.99 * cfg.fps:
            raise CameraError(f"camera {cfg.id}: asked for {cfg.fps:g} FPS at {cfg.width}x{cfg.height}, "
                              f"the device offers {got['fps']:g}")

    def settings(self) -> dict[str, Any]:
        return dict(self._readback)

    def start(self) -> None:
        # OpenCV starts streaming on the first grab; numbering starts afresh.
        self._sequencer = TimestampSequencer(self._readback.get("fps") or self.cfg.fps)
        self._counts = self._zero_counts()

    def read(self, timeout_s: float = 1.0) -> Frame | None:
        deadline = time.monotonic() + timeout_s
        while (remaining := deadline - time.monotonic()) > 0:
            timeout_ms = max(1, int(remaining * 1000))
            if timeout_ms != self._timeout_ms:
                self._dev.set("read_timeout_ms", timeout_ms)
                self._timeout_ms = timeout_ms
            got = self._dev.grab()
            if got is None:
                if not os.path.exists(self._dev.path):
                    raise CameraDisconnected(f"camera {self.cfg.id}: {self._dev.path} is gone")
                self._counts["timeouts"] += 1
                return None
            frame = self.process(*got, host_ns=time.clock_gettime_ns(time.CLOCK_MONOTONIC),
                                 real_ns=time.clock_gettime_ns(time.CLOCK_REALTIME))
            if frame is not None:
                return frame
        return None

    def process(self, buf: bytes, pos_msec: float, *, host_ns: int, real_ns: int) -> Frame | None:
        """One driver buffer to a Frame, or None for a buffer that is dropped (counted in stats)."""
        cfg = self.cfg
        if self._fourcc == "MJPG":
            jpeg = jpeg_trim(buf)
            header = jpeg_header(jpeg) if jpeg is not None else None
            if header is None:
                self._counts["corrupt"] += 1
                return None
            if (header.width, header.height) != (cfg.width, cfg.height):
                self._counts["size_mismatch"] += 1
                return None
            if not header.has_huffman:
                self._counts["tables_added"] += 1
            data, encoding = with_huffman_tables(jpeg, header), "jpeg"
        else:
            if len(buf) < cfg.width * cfg.height * 2:
                self._counts["corrupt"] += 1
                return None
            data, encoding = buf[:cfg.width * cfg.height * 2], "yuyv"
        t_device = buffer_time_to_monotonic_ns(pos_msec, host_ns, real_ns)
        if t_device is None:
            # Without a driver stamp the arrival time is the best there is.
            self._counts["no_timestamp"] += 1
            t_device = host_ns
        seq = self._sequencer(t_device)
        if seq is None:
            self._counts["repeated"] += 1
            return None
        self._counts["frames"] += 1
        self._counts["lost"] = self._sequencer.lost
        return Frame(data=data, seq=seq, t_device_ns=t_device, t_host_ns=host_ns,
                     width=cfg.width, height=cfg.height, encoding=encoding)

    def trigger(self) -> None:
        raise CameraError(f"camera {self.cfg.id}: UVC cameras cannot be triggered")

    def stats(self) -> dict[str, Any]:
        """frames, lost (inferred from timestamp gaps), corrupt, size_mismatch, repeated,
        tables_added, timeouts, no_timestamp, and the frame period the camera really runs at."""
        return {**self._counts, "period_ms": self._sequencer.period_ns / 1e6}

    def stop(self) -> None:
        """OpenCV cannot pause a V4L2 stream; frames are simply no longer read until close()."""

    def close(self) -> None:
        if self._opened:
            self._dev.release()
            self._opened = False

    def info(self) -> CameraInfo:
        got = self._readback
        name = Path(self.cfg.device).name
        return CameraInfo(id=self.cfg.id, backend=self.backend, model=_model_of(name), serial=_serial_of(name),
                          width=got.get("width", self.cfg.width), height=got.get("height", self.cfg.height),
                          fps=got.get("fps", self.cfg.fps), pixel_format=got.get("fourcc", self._fourcc),
                          can_trigger=False)


# -- discovery --------------------------------------------------------------------------------
def _by_id_parts(name: str) -> list[str]:
    # usb-<Vendor>_<Product>_<Serial>-video-index0: udev joins vendor, model and serial with '_'.
    stem = name.removeprefix("usb-").rsplit("-video-index", 1)[0]
    return stem.split("_")


def _serial_of(name: str) -> str:
    parts = _by_id_parts(name)
    return parts[-1] if len(parts) >= 3 else ""


def _model_of(name: str) -> str:
    parts = _by_id_parts(name)
    return " ".join(parts[:-1] if len(parts) >= 3 else parts)


def list_v4l2_cameras(by_id: Path = Path("/dev/v4l/by-id"),
                      sysfs: Path = Path("/sys/class/video4linux")) -> list[FoundCamera]:
    """Capture nodes under /dev/v4l/by-id (stable names across reboots and ports).

    UVC cameras also get a metadata node (index1); only index0, the image stream, is listed.
    """
    if not by_id.is_dir():
        return []
    found = []
    for link in sorted(by_id.iterdir()):
        if not link.name.endswith("-video-index0"):
            continue
        node = Path(os.path.realpath(link)).name
        name_file = sysfs / node / "name"
        model = name_file.read_text().strip() if name_file.is_file() else _model_of(link.name)
        found.append(FoundCamera(backend="v4l2", device=str(link), model=model,
                                 serial=_serial_of(link.name), address=f"/dev/{node}", protocol="UVC"))
    return found


def open_take(setup: TakeSetup) -> TakeCameras:
    return TakeCameras({c.id: V4l2Camera(c, sync=setup.rig.sync) for c in setup.cameras})


BACKEND = Backend("v4l2", open_take, discover=lambda fake: list_v4l2_cameras())
