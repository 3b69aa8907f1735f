"""GigE Vision and USB3 Vision cameras through Aravis 0.8 (gi.repository.Aravis).

Frames are handed out raw (the pixel format the camera sends, e.g. mono8 or bayer_rg8); the
recorder encodes them. Each frame carries the camera's block id unwrapped into a monotonic
`seq` (GigE Vision 1.x ids are 16 bits and skip 0), the device timestamp in ns (Aravis scales
the camera's ticks by its tick frequency) and the host time the buffer completed, moved from
CLOCK_REALTIME (what Aravis stamps) to CLOCK_MONOTONIC (what every other host time of a take
uses).
"""

from __future__ import annotations

import ipaddress
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from manus_core.errors import CameraDisconnected, CameraError
from manus_core.rig_config import CameraConfig

from . import Backend, CameraInfo, FoundCamera, Frame, TakeCameras, TakeSetup

# GenICam PixelFormat names -> Frame.encoding
ENCODINGS = {"Mono8": "mono8", "Mono10": "mono10", "Mono12": "mono12", "Mono16": "mono16",
             "BayerRG8": "bayer_rg8", "BayerGR8": "bayer_gr8", "BayerGB8": "bayer_gb8",
             "BayerBG8": "bayer_bg8", "RGB8": "rgb8", "RGB8Packed": "rgb8", "BGR8": "bgr8",
             "BGR8Packed": "bgr8", "YUV422Packed": "uyvy", "YUV422_8_UYVY": "uyvy"}

_ARAVIS: Any = None


def aravis() -> Any:
    """The Aravis 0.8 namespace; CameraError (with what to install) when it is missing."""
    global _ARAVIS
    if _ARAVIS is None:
        # PyGObject and Aravis are optional (the [aravis] extra and a system package): imported on
        # first use, so that the other backends, discovery and the recorder work without them
        try:
            import gi

            gi.require_version("Aravis", "0.8")
            from gi.repository import Aravis
        except (ImportError, ValueError) as exc:
            raise CameraError(f"Aravis 0.8 is not available ({exc}); install gir1.2-aravis-0.8 and "
                              "PyGObject (pip install 'manus-capture[aravis]')") from None
        _ARAVIS = Aravis
    return _ARAVIS


class FrameIdUnwrapper:
    """Block ids to a monotonic sequence number whose gaps are the frames lost.

    GigE Vision 1.x block ids run 1..65535 and wrap to 1 (0 is reserved), so steps are taken
    modulo 65535; ids above 65535 (GigE Vision 2 extended ids, USB3 Vision) never wrap in
    practice and are used as they are. A step backwards (a late or repeated id) returns the
    older number and leaves the sequence where it was.
    """

    RING = 0xFFFF

    def __init__(self) -> None:
        self._last: int | None = None
        self._seq = 0

    def __call__(self, raw: int) -> int:
        if self._last is None:
            self._last, self._seq = raw, raw
            return raw
        if raw > self.RING or self._last > self.RING:
            step = raw - self._last
        else:
            step = ((raw - 1) - (self._last - 1)) % self.RING
            if step > self.RING // 2:
                step -= self.RING
        if step <= 0:
            return self._seq + step
        self._last = raw
        self._seq += step
        return self._seq


def list_aravis_cameras(*, include_fake: bool = False, refresh: bool = True) -> list[FoundCamera]:
    """Every GigE Vision / USB3 Vision camera Aravis finds (GigE discovery takes about a second).

    include_fake also lists Aravis's in-process fake camera (Fake_1), handy without hardware.
    """
    arv = aravis()
    if include_fake:
        arv.enable_interface("Fake")
    if refresh:
        arv.update_device_list()
    found = []
    for i in range(arv.get_n_devices()):
        found.append(FoundCamera(backend="aravis", device=arv.get_device_id(i) or "",
                                 model=arv.get_device_model(i) or "", vendor=arv.get_device_vendor(i) or "",
                                 serial=arv.get_device_serial_nbr(i) or "",
                                 address=arv.get_device_address(i) or arv.get_device_physical_id(i) or "",
                                 protocol=arv.get_device_protocol(i) or ""))
    return found


def resolve_device(device: str) -> str:
    """rig.toml's `device` (Aravis id, serial number, IP address or physical id) to what
    Aravis.Camera.new opens. Aravis opens ids and addresses, not serial numbers, so those are
    looked up in the device list (refreshed only when the cached one lacks the camera)."""
    try:
        ipaddress.ip_address(device)
        return device
    except ValueError:
        pass
    for refresh in (False, True):
        for cam in list_aravis_cameras(refresh=refresh):
            if device in (cam.device, cam.serial, cam.address):
                return cam.device
    known = ", ".join(f"{c.device} (serial {c.serial})" for c in list_aravis_cameras(refresh=False))
    raise CameraError(f"Aravis camera {device!r} not found (found: {known or 'none'})")


def realtime_to_monotonic_ns(t_real_ns: int) -> int:
    """A CLOCK_REALTIME stamp on CLOCK_MONOTONIC, using the offset between the two clocks now."""
    offset = time.clock_gettime_ns(time.CLOCK_REALTIME) - time.clock_gettime_ns(time.CLOCK_MONOTONIC)
    return t_real_ns - offset


class AravisCamera:
    """One Aravis camera behind the Camera protocol.

    sync: "free-run" (the camera's own frame rate), "software-trigger" (one frame per
    trigger()), "hardware-trigger" (one frame per edge on `trigger_line`).
    """

    backend = "aravis"

    def __init__(self, cfg: CameraConfig, *, sync: str = "free-run", n_buffers: int = 16,
                 trigger_line: str = "Line0") -> None:
        self.cfg = cfg
        self.sync = sync
        self.n_buffers = n_buffers
        self.trigger_line = trigger_line
        self._cam: Any = None
        self._stream: Any = None
        self._lost = threading.Event()
        self._handler: int | None = None
        self._unwrap = FrameIdUnwrapper()
        self._readback: dict[str, Any] = {}
        self._counts = {"frames": 0, "incomplete": 0, "seq_gaps": 0}
        self._last_seq: int | None = None
        self._tick_hz: int | None = None
        self._encoding = ENCODINGS.get(cfg.pixel_format, cfg.pixel_format.lower())

    @contextmanager
    def _guard(self, what: str) -> Iterator[None]:
        from gi.repository import GLib  # optional, as in aravis(); loaded by then

        try:
            yield
        except GLib.Error as exc:
            raise CameraError(f"camera {self.cfg.id} ({self.cfg.device}): {what}: {exc.message}") from None

    def open(self) -> None:
        arv = aravis()
        device = resolve_device(self.cfg.device)
        with self._guard("cannot open"):
            self._cam = arv.Camera.new(device)
        dev = self._cam.get_device()
        # Emitted from Aravis's heartbeat thread when the camera stops answering.
        self._handler = dev.connect("control-lost", lambda *_: self._lost.set())
        if hasattr(dev, "get_timestamp_tick_frequency"):
            self._tick_hz = int(dev.get_timestamp_tick_frequency())
        else:
            self._tick_hz = 1_000_000_000   # USB3 Vision timestamps are ns by the standard

    def configure(self) -> None:
        cam, cfg = self._need_open(), self.cfg
        with self._guard("pixel format"):
            offered = list(cam.dup_available_pixel_formats_as_strings())
            if cfg.pixel_format not in offered:
                raise CameraError(f"camera {cfg.id}: pixel format {cfg.pixel_format!r} is not offered "
                                  f"(offers {', '.join(offered)})")
            cam.set_pixel_format_from_string(cfg.pixel_format)
        # Bounds are checked here for a message that names them: not every camera's GenICam
        # description enforces its own limits (Aravis's fake camera takes any width).
        with self._guard(f"region {cfg.width}x{cfg.height}"):
            self._within("width", cfg.width, cam.get_width_bounds())
            self._within("height", cfg.height, cam.get_height_bounds())
            cam.set_region(0, 0, cfg.width, cfg.height)
        with self._guard(f"frame rate {cfg.fps:g}"):
            self._within("frame rate", cfg.fps, cam.get_frame_rate_bounds())
            cam.set_frame_rate(cfg.fps)
        with self._guard(f"exposure {cfg.exposure_us:g} µs"):
            self._within("exposure (µs)", cfg.exposure_us, cam.get_exposure_time_bounds())
            cam.set_exposure_time(cfg.exposure_us)
        with self._guard(f"gain {cfg.gain_db:g} dB"):
            if cam.is_gain_available():
                self._within("gain", cfg.gain_db, cam.get_gain_bounds())
                cam.set_gain(cfg.gain_db)
        # After the frame rate: Aravis's set_frame_rate switches the FrameStart trigger off.
        with self._guard(f"trigger ({self.sync})"):
            if self.sync == "software-trigger":
                cam.set_trigger("Software")
            elif self.sync == "hardware-trigger":
                cam.set_trigger(self.trigger_line)
            else:
                cam.clear_triggers()
        self._readback = self.settings()
        _, _, width, height = self._readback["region"]
        if (width, height) != (cfg.width, cfg.height):
            raise CameraError(f"camera {cfg.id}: asked for {cfg.width}x{cfg.height}, the camera gave "
                              f"{width}x{height}")
        if self.sync == "free-run" and self._readback["fps"] < 0.99 * cfg.fps:
            raise CameraError(f"camera {cfg.id}: asked for {cfg.fps:g} FPS, the camera runs at "
                              f"{self._readback['fps']:g} (exposure {self._readback['exposure_us']:g} µs)")

    def _within(self, what: str, value: float, bounds: Any) -> None:
        low, high = bounds.min, bounds.max
        if not low <= value <= high:
            raise CameraError(f"camera {self.cfg.id}: {what} {value:g} is outside {low:g}..{high:g}")

    def settings(self) -> dict[str, Any]:
        """The camera's features as read back (cameras round what they are given)."""
        cam = self._need_open()
        dev = cam.get_device()
        with self._guard("read back features"):
            region = cam.get_region()
            out = {"region": (region.x, region.y, region.width, region.height),
                   "pixel_format": cam.get_pixel_format_as_string(),
                   "fps": cam.get_frame_rate(), "exposure_us": cam.get_exposure_time(),
                   "gain_db": cam.get_gain() if cam.is_gain_available() else None,
                   "trigger_mode": dev.get_string_feature_value("TriggerMode"),
                   "trigger_source": dev.get_string_feature_value("TriggerSource"),
                   "tick_hz": self._tick_hz}
        return out

    def start(self) -> None:
        arv, cam = aravis(), self._need_open()
        with self._guard("start streaming"):
            payload = cam.get_payload()
            self._stream = cam.create_stream(None, None)
            for _ in range(self.n_buffers):
                self._stream.push_buffer(arv.Buffer.new_allocate(payload))
            self._unwrap = FrameIdUnwrapper()
            self._last_seq = None
            cam.start_acquisition()
        pixel_format = self._readback.get("pixel_format") or self.cfg.pixel_format
        self._encoding = ENCODINGS.get(pixel_format, pixel_format.lower())

    def read(self, timeout_s: float = 1.0) -> Frame | None:
        """The next complete frame, or None after timeout_s; incomplete buffers are recycled
        (their ids become gaps in seq)."""
        arv, stream = aravis(), self._stream
        if stream is None:
            raise CameraError(f"camera {self.cfg.id}: read() before start()")
        deadline = time.monotonic() + timeout_s
        while True:
            if self._lost.is_set():
                raise CameraDisconnected(f"camera {self.cfg.id} ({self.cfg.device}): control lost")
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            # Short pops so that a lost camera is noticed while waiting.
            buf = stream.timeout_pop_buffer(int(min(remaining, 0.1) * 1e6))
            if buf is None:
                continue
            if buf.get_status() != arv.BufferStatus.SUCCESS:
                self._counts["incomplete"] += 1
                stream.push_buffer(buf)
                continue
            frame = Frame(data=buf.get_data(), seq=self._unwrap(buf.get_frame_id()),
                          t_device_ns=buf.get_timestamp(),
                          t_host_ns=realtime_to_monotonic_ns(buf.get_system_timestamp()),
                          width=buf.get_image_width(), height=buf.get_image_height(),
                          encoding=self._encoding)
            stream.push_buffer(buf)
            self._counts["frames"] += 1
            if self._last_seq is not None and frame.seq > self._last_seq + 1:
                self._counts["seq_gaps"] += frame.seq - self._last_seq - 1
            self._last_seq = frame.seq if self._last_seq is None else max(frame.seq, self._last_seq)
            return frame

    def trigger(self) -> None:
        if self.sync != "software-trigger":
            raise CameraError(f"camera {self.cfg.id}: trigger() needs sync 'software-trigger' (is {self.sync})")
        with self._guard("software trigger"):
            self._need_open().software_trigger()

    def stats(self) -> dict[str, Any]:
        """Frames handed out, incomplete buffers, seq gaps, and Aravis's stream counters
        (n_missing_frames, n_underruns, n_missing_packets, n_resent_packets, ...)."""
        from gi.repository import GObject  # optional, as in aravis(); loaded by then

        out: dict[str, Any] = dict(self._counts)
        stream = self._stream
        if stream is not None:
            for i in range(stream.get_n_infos()):
                kind = stream.get_info_type(i)
                if kind == GObject.TYPE_UINT64:
                    out[stream.get_info_name(i)] = stream.get_info_uint64(i)
                elif kind == GObject.TYPE_DOUBLE:
                    out[stream.get_info_name(i)] = stream.get_info_double(i)
        return out

    def stop(self) -> None:
        if self._cam is None or self._stream is None:
            return
        if self._lost.is_set():
            held, self._stream = [self._stream], None
            self._release_aside(held)
            return
        with self._guard("stop streaming"):
            self._cam.stop_acquisition()
        self._stream = None

    def close(self) -> None:
        if self._cam is None:
            return
        self.stop()
        if self._handler is not None:
            self._cam.get_device().disconnect(self._handler)
            self._handler = None
        # Dropping the last references lets Aravis release the camera's control channel.
        held, self._cam = [self._cam], None
        if self._lost.is_set():
            self._release_aside(held)

    def _release_aside(self, held: list) -> None:
        # Aravis's teardown of a camera that no longer answers waits out the protocol's retries
        # (seconds per object); the last reference is dropped on a thread of its own so that
        # the recorder's other cameras do not wait for it. `held` must be that last reference.
        threading.Thread(target=held.clear, name=f"release-{self.cfg.id}", daemon=True).start()

    def info(self) -> CameraInfo:
        cam = self._need_open()
        settings = self._readback or self.settings()
        with self._guard("info"):
            sources = list(cam.dup_available_trigger_sources() or [])
            model = cam.get_model_name() or ""
            serial = cam.get_device_serial_number() or ""
        return CameraInfo(id=self.cfg.id, backend=self.backend, model=model, serial=serial,
                          width=settings["region"][2], height=settings["region"][3], fps=settings["fps"],
                          pixel_format=settings["pixel_format"], can_trigger="Software" in sources)

    def _need_open(self) -> Any:
        if self._cam is None:
            raise CameraError(f"camera {self.cfg.id}: not open")
        return self._cam


def open_take(setup: TakeSetup) -> TakeCameras:
    return TakeCameras({c.id: AravisCamera(c, sync=setup.rig.sync) for c in setup.cameras})


BACKEND = Backend("aravis", open_take, discover=lambda fake: list_aravis_cameras(include_fake=fake))
