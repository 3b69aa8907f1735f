"""The recorder: every camera of a rig into one take folder (DESIGN.md, "On disk"; stage 1).

    reader thread per camera --(bounded ring)--> writer thread per camera --> cams/CAM.mkv
                                                                        \\--> frames.csv (shared)

A reader only pulls frames from its camera and never waits on the disk: a full ring costs a
frame (counted as an overflow, visible as a sequence gap) rather than stalling the camera's own
buffers. A writer muxes the JPEG bytes as they came (raw frames from machine-vision cameras are
JPEG-encoded first) and appends the frame's row to frames.csv only after its packet is written,
so that rows and packets agree. Every file stays readable if the process dies (see rig/mkv.py);
an orderly stop (end of the duration, Ctrl-C, SIGTERM, a full disk, a failing writer) finishes
every file and writes take.json with the status and the reason.

Time: one clock per take. Real rigs use CLOCK_MONOTONIC; the simulated rig its virtual clock, on
which every frame, tick and LED event of the take is expressed (take.json says which).
"""

from __future__ import annotations

import bisect
import contextlib
import errno
import json
import math
import os
import queue
import shutil
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from manus_core.fileio import write_atomic

from .cameras import Camera, CameraDisconnected, Frame
from .clock import Clock, MonotonicClock, VirtualClock
from manus_core.rig_config import RigConfig
from .mkv import MkvWriter
from manus_core.session import check_kind, check_take_name, open_session, utc_now
from manus_core.errors import DiskSpaceError, RecordError

FRAME_COLUMNS = "cam,seq,t_device_ns,t_host_ns,bytes,flags"
FLAG_HOST_JPEG = 1            # frames.csv flags bit: the host encoded a raw frame to JPEG
BALLAST_BYTES = 32 * 2**20    # reserved at the start, released to finish the take on a full disk
JPEG_BYTES_BASE = 2000        # estimate of a JPEG frame: header + entropy-coded pixels
# q90 of the simulated cube at 720p measures 0.22 B/px with colour at full resolution (4:2:0: 0.17);
# the estimate errs on the safe side
JPEG_BYTES_PER_PIXEL = 0.25
REAL_LEAD_NS = 50_000_000     # real rigs: tick 0 comes this long after the cameras started
READ_TIMEOUT_S = 0.2          # how often a reader looks at the stop flag
STALL_S = 2.0                 # a camera that hands out nothing for this long has stopped
FIRST_FRAME_S = 5.0           # ... except before its first frame (streams take time to start)
JOIN_S = 10.0                 # a reader whose read() never returns is abandoned after this
WRITE_BATCH = 32              # frames a writer that fell behind stores in one system call


class StopFlag:
    """Why a take ends before its duration; the first reason wins.

    A signal handler runs between two bytecodes of the main thread, which may hold any lock at
    that moment, so signal() takes none: it only notes the reason, and the next is_set() or
    wait() (the main thread polls every 50 ms) turns it into the stop.
    """

    def __init__(self) -> None:
        self._event = threading.Event()
        self._lock = threading.Lock()
        self._signalled: str | None = None
        self.reason = ""
        self.by_signal = False

    def set(self, reason: str, *, by_signal: bool = False) -> None:
        with self._lock:
            if not self._event.is_set():
                self.reason, self.by_signal = reason, by_signal
                self._event.set()

    def signal(self, reason: str) -> None:
        """From a signal handler: ask for the stop without taking a lock."""
        self._signalled = reason

    @property
    def requested(self) -> bool:
        """Whether a stop was asked for (lock-free, for signal handlers)."""
        return self._signalled is not None or self._event.is_set()

    def is_set(self) -> bool:
        if self._signalled is not None and not self._event.is_set():
            self.set(self._signalled, by_signal=True)
        return self._event.is_set()

    def wait(self, timeout: float) -> bool:
        if not self.is_set():
            self._event.wait(timeout)
        return self.is_set()


@dataclass
class CameraReport:
    """What one camera delivered in a take (take.json "cameras")."""

    id: str
    backend: str
    width: int
    height: int
    fps: float
    pixel_format: str
    exposure_us: float | None = None
    latency_ms: float | None = None  # exposure end -> earliest host arrival, where the rig knows it
    model: str = ""
    serial: str = ""
    encoding: str = ""
    frames: int = 0           # rows in frames.csv = packets in cams/ID.mkv
    bytes: int = 0
    first_seq: int | None = None
    last_seq: int | None = None
    seq_gaps: int = 0         # frames missing between first_seq and last_seq (camera, link or host)
    overflows: int = 0        # of which the host lost because the ring buffer was full
    unwritten: int = 0        # received but not stored because the writer had failed
    status: str = "ok"        # ok | disconnected | stopped | failed
    error: str = ""
    t_lost_ns: int | None = None


@dataclass
class TakeResult:
    path: Path
    status: str               # complete | interrupted
    reason: str
    by_signal: bool
    cameras: list[CameraReport]
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def frames(self) -> int:
        return sum(c.frames for c in self.cameras)

    @property
    def lost(self) -> list[CameraReport]:
        return [c for c in self.cameras if c.status != "ok"]

    @property
    def exit_code(self) -> int:
        """0 complete with every camera; 130 stopped by a signal; 1 any other fault."""
        if self.status == "interrupted" and self.by_signal:
            return 130
        return 1 if self.status == "interrupted" or self.lost else 0


# -- clocks ---------------------------------------------------------------------------------
def is_fast(clock: Clock) -> bool:
    """A virtual clock at time_scale 0: time moves only when the simulation reports it."""
    return isinstance(clock, VirtualClock) and clock.time_scale == 0


def wait_until(clock: Clock, t_ns: int, stop: StopFlag) -> bool:
    """Wait on `clock` until t_ns; False if the take was stopped meanwhile."""
    if is_fast(clock):
        clock.sleep_until_ns(t_ns)
        return not stop.is_set()
    scale = getattr(clock, "time_scale", 1.0)
    while True:
        delay = (t_ns - clock.now_ns()) / 1e9 / scale
        if delay <= 0:
            return not stop.is_set()
        if stop.wait(min(delay, 0.1)):
            return False


class SimTakeClock(VirtualClock):
    """The simulated host clock of a take, where a thread can pin its own 'now'.

    At time_scale 0 the clock is the latest time any camera reported, and a camera reports its
    frame's arrival, which in real time would lie a few ms ahead. The software-trigger thread pins
    its time to the tick while it triggers, so a trigger is stamped with the tick it was sent on,
    as it would be in real time.
    """

    def __init__(self, start_ns: int | None = None, time_scale: float = 0.0) -> None:
        super().__init__(start_ns, time_scale)
        self._pin = threading.local()

    def now_ns(self) -> int:
        pinned = getattr(self._pin, "t_ns", None)
        return super().now_ns() if pinned is None else pinned

    @contextlib.contextmanager
    def pinned(self, t_ns: int) -> Iterator[None]:
        self._pin.t_ns = int(t_ns)
        try:
            yield
        finally:
            self._pin.t_ns = None


# -- LEDs -----------------------------------------------------------------------------------
def flash_offsets(duration_s: float, flash_ms: float, every_s: float) -> list[float]:
    """Flash start times (s after tick 0): centred in consecutive windows of every_s seconds;
    a take shorter than one window gets one flash in its middle."""
    length = flash_ms / 1000
    if length >= duration_s:
        return []
    starts = [every_s * (k + 0.5) - length / 2 for k in range(int(duration_s // every_s))]
    starts = [s for s in starts if s + length <= duration_s]
    return starts or [(duration_s - length) / 2]


class LedPlan:
    """The take's LED commands, placed on the take's clock, and the lighting they give the sim.

    Each level or flash command gets an anchor (take-clock time, CLOCK_MONOTONIC send time,
    settle time). On CLOCK_MONOTONIC the two times coincide. On the simulated clock the anchor
    ties them together: an exposure at take time t after anchor a sees what the controller showed
    at a.t_send + min(t - a.t_clock, a.settle), where settle covers the acknowledgement and a
    flash's length. At time_scale 0 commands go out as soon as the previous flash has run its
    course in real time (the controller times flashes itself), and an exposure at take time t
    waits until every command planned at or before t has been sent, so that a frame never misses
    a flash because the renderer ran ahead of the LED thread.
    """

    def __init__(self, controller: Any, clock: Clock, stop: StopFlag) -> None:
        self.controller = controller
        self.clock = clock
        self.stop = stop
        self.virtual = isinstance(clock, VirtualClock)
        self.fast = is_fast(clock)
        self.device = getattr(controller, "sim", None)   # the simulated controller, if it is one
        self.flashes: list[dict[str, Any]] = []
        self.errors: list[str] = []
        self.trigger: dict[str, Any] | None = None
        self._anchors: list[tuple[int, int, int]] = []
        self._pending: list[int] = []
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None

    def _anchor(self, t_clock: int, record: dict[str, Any], extra_ns: int = 0) -> None:
        send = int(record["t_send_ns"])
        settle = int(record.get("t_ack_ns") or record.get("t_done_ns") or send) - send + extra_ns
        with self._cond:
            bisect.insort(self._anchors, (t_clock, send, settle))
            with contextlib.suppress(ValueError):
                self._pending.remove(t_clock)
            self._cond.notify_all()

    def to_clock(self, t_send_ns: int) -> int:
        """A CLOCK_MONOTONIC time of the LED log on the take's clock."""
        if not self.virtual or not self._anchors:
            return int(t_send_ns)
        by_send = sorted(self._anchors, key=lambda a: a[1])
        i = max(0, bisect.bisect_right([a[1] for a in by_send], t_send_ns) - 1)
        t_clock, send, _ = by_send[i]
        return t_clock + int(t_send_ns) - send

    def set_level(self, level: float) -> None:
        t = self.clock.now_ns()
        self._anchor(t, self.controller.on(level))

    def plan_flashes(self, times_ns: Sequence[int], ms: int, level: float) -> threading.Thread:
        """Mark the flashes as planned (exposures after them wait) and return their thread, not started."""
        times = sorted(int(t) for t in times_ns)
        with self._cond:
            self._pending = list(times)
        self._thread = threading.Thread(target=self._flash_loop, args=(times, ms, level),
                                        name="leds", daemon=True)
        return self._thread

    def _flash_loop(self, times: list[int], ms: int, level: float) -> None:
        from .leds import LedError

        try:
            for t in times:
                if not self.fast and not wait_until(self.clock, t, self.stop):
                    break
                if self.stop.is_set():
                    break
                t_clock = t if self.fast else self.clock.now_ns()
                with self._cond:   # scaled clocks send a little after the plan: move the wait mark
                    self._pending = [t_clock if p == t else p for p in self._pending]
                record = self.controller.flash(ms, level)
                self._anchor(t_clock, record, ms * 1_000_000)
                ack = record.get("t_ack_ns") or record["t_send_ns"]
                self.flashes.append({"seq": record.get("seq"), "ms": ms, "level": level, "t_clock_ns": t_clock,
                                     "t_ack_clock_ns": t_clock + int(ack) - int(record["t_send_ns"])})
                if self.fast:
                    # the controller times the flash in real time: the next command must not cut it short
                    time.sleep(ms / 1000 + 0.002)
        except LedError as exc:
            self.errors.append(f"flash: {exc}")
        finally:
            self.cancel()

    def cancel(self) -> None:
        """Drop the commands not sent yet; exposures stop waiting for them."""
        with self._cond:
            self._pending.clear()
            self._cond.notify_all()

    def join(self) -> None:
        self.cancel()
        if self._thread is not None:
            self._thread.join()

    def lighting(self, t_ns: int) -> float:
        """The simulated panels' mean level (0..1) at take-clock time t_ns (SimulatedCube's lighting)."""
        with self._cond:
            while self._pending and self._pending[0] <= t_ns:
                self._cond.wait(0.05)
            i = bisect.bisect_right(self._anchors, (t_ns, math.inf, math.inf)) - 1
            if i < 0:
                if not self._anchors:
                    return 0.0
                real = self._anchors[0][1] - 1   # before the first command: what the panels showed then
            else:
                t_clock, send, settle = self._anchors[i]
                real = send + min(t_ns - t_clock, settle)
        return float(np.mean(self.device.state_at(real)))

    def start_trigger(self, rate_hz: float) -> None:
        record = self.controller.trigger(rate_hz)
        reply = record.get("reply", {})
        self.trigger = {"rate_hz": rate_hz, "seq": record.get("seq"), "t_clock_ns": self.to_clock(record["t_send_ns"]),
                        "p0": int(reply["p0"]) if "p0" in reply else None,
                        "t0_controller_us": int(reply["t0"]) if "t0" in reply else None}

    def stop_trigger(self) -> None:
        from .leds import LedError

        try:
            status = self.controller.status()
            self.controller.stop_trigger()
        except LedError as exc:
            self.errors.append(f"stop trigger: {exc}")
            return
        if self.trigger is not None and self.trigger.get("p0") is not None:
            self.trigger["pulses"] = int(status.get("pulses", 0)) - self.trigger["p0"]

    def log(self) -> list[dict[str, Any]]:
        """The controller's command log; on a virtual clock each entry also gets t_clock_ns."""
        records = self.controller.records()
        if self.virtual:
            for r in records:
                t = r.get("t_send_ns", r.get("t_ns"))
                if t is not None:
                    r["t_clock_ns"] = self.to_clock(int(t))
        return records


# -- frames ---------------------------------------------------------------------------------
_BAYER = {"bayer_rg8": "COLOR_BayerRGGB2BGR", "bayer_gr8": "COLOR_BayerGRBG2BGR",
          "bayer_gb8": "COLOR_BayerGBRG2BGR", "bayer_bg8": "COLOR_BayerBGGR2BGR"}
_HIGH_BIT = {"mono10": 2, "mono12": 4, "mono16": 8}


_BYTES_PER_PIXEL = {"mono8": 1, **dict.fromkeys(_HIGH_BIT, 2), **dict.fromkeys(_BAYER, 1),
                    "bgr8": 3, "rgb8": 3, "uyvy": 2, "yuyv": 2}


def frame_jpeg(frame: Frame, params: list[int]) -> tuple[bytes, int]:
    """(JPEG bytes, frames.csv flags): JPEG frames as they came; raw pixels encoded with the
    cv2.imencode `params` (StorageConfig.jpeg_params)."""
    if frame.encoding == "jpeg":
        return frame.data, 0
    import cv2

    w, h, enc = frame.width, frame.height, frame.encoding
    if enc not in _BYTES_PER_PIXEL:
        raise ValueError(f"pixel encoding {enc!r} cannot be stored (known: jpeg, {', '.join(_BYTES_PER_PIXEL)})")
    if len(frame.data) < w * h * _BYTES_PER_PIXEL[enc]:
        raise ValueError(f"a {enc} frame of {len(frame.data)} bytes is too short for {w}x{h}")
    buf = np.frombuffer(frame.data, np.uint8)
    if enc == "mono8":
        image = buf[:w * h].reshape(h, w)
    elif enc in _HIGH_BIT:
        image = (np.frombuffer(frame.data, "<u2")[:w * h].reshape(h, w) >> _HIGH_BIT[enc]).astype(np.uint8)
    elif enc in _BAYER:
        image = cv2.cvtColor(buf[:w * h].reshape(h, w), getattr(cv2, _BAYER[enc]))
    elif enc in ("bgr8", "rgb8"):
        image = buf[:w * h * 3].reshape(h, w, 3)
        if enc == "rgb8":
            image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    else:
        code = cv2.COLOR_YUV2BGR_UYVY if enc == "uyvy" else cv2.COLOR_YUV2BGR_YUY2
        image = cv2.cvtColor(buf[:w * h * 2].reshape(h, w, 2), code)
    ok, out = cv2.imencode(".jpg", image, params)
    if not ok:
        raise ValueError(f"JPEG encoding of a {w}x{h} {enc} frame failed")
    return out.tobytes(), FLAG_HOST_JPEG


class _CsvSink:
    """frames.csv, shared by the writers: whole rows only, even when the disk fills up."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._lock = threading.Lock()
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o644)
        self._size = 0
        self.append((FRAME_COLUMNS + "\n").encode())

    def append(self, row: bytes) -> None:
        with self._lock:
            done = 0
            try:
                while done < len(row):
                    n = os.write(self._fd, row[done:])
                    if n == 0:
                        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self.path))
                    done += n
            except OSError as exc:
                os.ftruncate(self._fd, self._size)
                os.lseek(self._fd, self._size, os.SEEK_SET)
                raise OSError(exc.errno, exc.strerror, str(self.path)) from exc
            self._size += done

    def close(self) -> None:
        with self._lock:
            if self._fd is not None:
                with contextlib.suppress(OSError):
                    os.fsync(self._fd)
                os.close(self._fd)
                self._fd = None


_END = object()


class _Stream:
    """One camera: its reader thread, ring buffer, writer thread and report."""

    def __init__(self, rec: Recorder, cam_id: str, camera: Camera, report: CameraReport, ring: int) -> None:
        self.rec, self.id, self.camera, self.report = rec, cam_id, camera, report
        self.ring: queue.Queue = queue.Queue(maxsize=ring)
        self.mkv: MkvWriter | None = None
        self.write_failed = False
        self.abandoned = False
        self.last_t_host: int | None = None
        self.reader = threading.Thread(target=self._read_loop, name=f"read-{cam_id}", daemon=True)
        self.writer = threading.Thread(target=self._write_loop, name=f"write-{cam_id}", daemon=True)

    @property
    def active(self) -> bool:
        return self.report.status == "ok" and self.reader.is_alive()

    def lost(self, status: str, message: str) -> None:
        self.report.status, self.report.error = status, message
        self.report.t_lost_ns = self.rec.clock.now_ns()
        self.rec.event(self.id, status, message)

    def _read_loop(self) -> None:
        rec, cam = self.rec, self.camera
        last_frame = time.monotonic()
        got_any = False
        try:
            while not rec.stop.is_set():
                try:
                    frame = cam.read(rec.read_timeout_s)
                except CameraDisconnected as exc:
                    self.lost("disconnected", str(exc))
                    break
                except Exception as exc:   # any backend failure takes out this camera only
                    self.lost("failed", f"{type(exc).__name__}: {exc}")
                    break
                if frame is None:
                    if rec.clock.now_ns() >= rec.end_ns:
                        break
                    idle = time.monotonic() - last_frame
                    if idle > (rec.stall_s if got_any else max(rec.stall_s, FIRST_FRAME_S)):
                        self.lost("stopped", f"no frame for {idle:.1f} s")
                        break
                    continue
                got_any = True
                last_frame = time.monotonic()
                self.last_t_host = frame.t_host_ns
                try:
                    self.ring.put_nowait(frame)
                except queue.Full:
                    self.report.overflows += 1
                # the first frame that arrives at or after the end is kept: every frame read is stored
                if frame.t_host_ns >= rec.end_ns:
                    break
        finally:
            self.ring.put(_END)

    def _write_loop(self) -> None:
        rec, report = self.rec, self.report
        try:
            ended = False
            while not ended:
                try:
                    item = self.ring.get(timeout=0.5)
                except queue.Empty:
                    if self.abandoned:
                        break
                    continue
                # whatever queued up meanwhile goes out in one write: a writer that fell behind
                # catches up with fewer system calls per frame
                batch: list[Frame] = []
                while True:
                    if item is _END:
                        ended = True
                        break
                    batch.append(item)
                    if len(batch) == WRITE_BATCH:
                        break
                    try:
                        item = self.ring.get_nowait()
                    except queue.Empty:
                        break
                if batch and not self.write_failed:
                    self._store_or_fail(batch)
                elif batch:
                    report.unwritten += len(batch)
        finally:
            if self.mkv is not None:
                try:
                    self.mkv.close()
                except OSError as exc:
                    rec.event(self.id, "finish-failed", str(exc))

    def _store_or_fail(self, batch: list[Frame]) -> None:
        try:
            self._store(batch)
            return
        except Exception as exc:
            error, left = exc, batch
        if len(batch) > 1:
            # the batch failed as a whole: store its frames one by one as far as they go
            for i, frame in enumerate(batch):
                try:
                    self._store([frame])
                except Exception as exc:
                    error, left = exc, batch[i:]
                    break
            else:
                return
        self.write_failed = True
        self.report.unwritten += len(left)
        self.rec.stop.set(self._failure(error))

    def _failure(self, exc: Exception) -> str:
        name = Path(getattr(exc, "filename", None) or self.mkv.path)
        with contextlib.suppress(ValueError):
            name = name.relative_to(self.rec.path)
        if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
            return f"disk full (ENOSPC) while writing {name}"
        return f"writer of camera {self.id} failed: {type(exc).__name__}: {exc}"

    def _store(self, frames: list[Frame]) -> None:
        """Packets first, then their frames.csv rows; rows that cannot be written take their
        packets back out, so that rows and packets always agree."""
        report = self.report
        datas, rows = [], []
        for frame in frames:
            data, flags = frame_jpeg(frame, self.rec.jpeg_params)
            datas.append(data)
            rows.append(f"{self.id},{frame.seq},{frame.t_device_ns},{frame.t_host_ns},{len(data)},{flags}\n")
        self.mkv.write(datas)
        try:
            self.rec.csv.append("".join(rows).encode())
        except OSError:
            self.mkv.rollback()
            raise
        for frame, data in zip(frames, datas):
            if report.last_seq is not None and frame.seq > report.last_seq + 1:
                report.seq_gaps += frame.seq - report.last_seq - 1
            if report.first_seq is None:
                report.first_seq = frame.seq
            report.last_seq = frame.seq if report.last_seq is None else max(report.last_seq, frame.seq)
            report.bytes += len(data)
            report.encoding = frame.encoding
        report.frames += len(frames)


class Recorder:
    """Record `cameras` (opened here) into the take folder `path` for duration_s on `clock`.

    t0_ns is the take's tick 0 (the sim cube's; for real rigs REAL_LEAD_NS after the cameras
    start); the take ends at t0 + duration. `leds` is an open LED controller (or None), or
    `plan` a LedPlan made with the same clock and StopFlag; `on_stop` runs after the cameras
    are closed and returns extra take.json fields.
    """

    def __init__(self, rig: RigConfig, path: str | Path, kind: str, duration_s: float,
                 cameras: Mapping[str, Camera], clock: Clock, *, take: str | None = None,
                 t0_ns: int | None = None, leds: Any = None, plan: LedPlan | None = None,
                 level: float | None = None, flash_ms: int | None = None, flash_every_s: float = 1.0,
                 flash_level: float | None = None, stop: StopFlag | None = None, buffer_s: float = 0.5,
                 read_timeout_s: float = READ_TIMEOUT_S, stall_s: float = STALL_S, progress: bool = True,
                 fsync: bool = True, backend_note: str = "",
                 on_stop: Callable[[], dict[str, Any]] | None = None) -> None:
        self.rig, self.path, self.kind = rig, Path(path), check_kind(kind)
        self.take = take or self.path.name
        self.duration_s = float(duration_s)
        self.cameras = dict(cameras)
        self.clock = clock
        self.stop = stop or StopFlag()
        self.plan = plan if plan is not None else (LedPlan(leds, clock, self.stop) if leds is not None else None)
        self.level, self.flash_ms, self.flash_every_s = level, flash_ms, flash_every_s
        self.flash_level = flash_level
        self.read_timeout_s, self.stall_s, self.progress, self.fsync = read_timeout_s, stall_s, progress, fsync
        self.storage = rig.storage
        self.jpeg_params = rig.storage.jpeg_params()
        self.backend_note = backend_note
        self.on_stop = on_stop
        self.t0_ns = t0_ns
        self.end_ns = sys.maxsize
        self.events: list[dict[str, Any]] = []
        self._events_lock = threading.Lock()
        self.ticks: dict[str, list[int]] = {"tick": [], "t_sent_ns": [], "t_sent_last_ns": []}
        configs = {c.id: c for c in rig.cameras}
        self.streams: list[_Stream] = []
        for cam_id, camera in self.cameras.items():
            c = configs[cam_id]
            # the sync stage needs the transfer latency floor to tell it from a clock offset; the
            # simulated cameras declare theirs in rig.toml
            report = CameraReport(cam_id, c.backend, c.width, c.height, c.fps, c.pixel_format, c.exposure_us,
                                  c.sim.latency_ms if c.sim is not None else None)
            self.streams.append(_Stream(self, cam_id, camera, report, max(8, math.ceil(c.fps * buffer_s))))
        self.csv: _CsvSink | None = None
        self.start_ns: int | None = None
        self.stop_ns: int | None = None
        self.created = utc_now()

    @property
    def led_level(self) -> float:
        """The take's LED set-point: --level, else the controller's default ([leds] level)."""
        return self.level if self.level is not None else self.plan.controller.default_level

    def event(self, cam: str, what: str, message: str) -> None:
        with self._events_lock:
            self.events.append({"t_ns": self.clock.now_ns(), "cam": cam, "event": what, "message": message})

    # -- the take ---------------------------------------------------------------------------
    def run(self) -> TakeResult:
        """Open, stream, stop, finish; always leaves a readable take folder behind."""
        (self.path / "cams").mkdir(parents=True, exist_ok=True)
        ballast = self.path / ".reserve"
        _reserve(ballast, BALLAST_BYTES)
        self.csv = _CsvSink(self.path / "frames.csv")
        self._write_meta("recording", "")
        opened: list[Camera] = []
        try:
            for s in self.streams:
                s.camera.open()
                opened.append(s.camera)
                s.camera.configure()
                self._describe(s)
                r = s.report
                s.mkv = MkvWriter(self.path / "cams" / f"{s.id}.mkv", r.width, r.height, r.fps,
                                  name=s.id, fsync=self.fsync)
            if self.plan is not None:
                self.plan.set_level(self.led_level)
            self._stream_all()
        except BaseException as exc:
            # the take still ends in order: readers see the flag, writers finish their files
            self.stop.set(f"recorder error: {type(exc).__name__}: {exc}")
            raise
        finally:
            self._close_cameras(opened)
            for s in self.streams:
                if s.writer.is_alive():
                    s.writer.join()
                elif s.mkv is not None:
                    s.mkv.close()
            self.csv.close()
            with contextlib.suppress(FileNotFoundError):
                ballast.unlink()
            if self.stop.reason.startswith("recorder error"):
                with contextlib.suppress(Exception):
                    self._write_meta("interrupted", self.stop.reason)
        status = "interrupted" if self.stop.is_set() else "complete"
        extra = self.on_stop() if self.on_stop is not None else {}
        meta = self._write_meta(status, self.stop.reason, extra)
        return TakeResult(self.path, status, self.stop.reason, self.stop.by_signal,
                          [s.report for s in self.streams], meta)

    def _describe(self, s: _Stream) -> None:
        with contextlib.suppress(Exception):   # info() is descriptive only; a backend may not have it yet
            info = s.camera.info()
            s.report.model, s.report.serial = info.model, info.serial

    def _stream_all(self) -> None:
        for s in self.streams:
            s.camera.start()
        self.start_ns = self.clock.now_ns()
        if self.t0_ns is None:
            self.t0_ns = self.start_ns + REAL_LEAD_NS
        self.end_ns = self.t0_ns + int(round(self.duration_s * 1e9))
        flashes = None
        if self.plan is not None and self.flash_ms:
            level = self.flash_level
            if level is None:   # most contrast against the set-point
                level = 0.0 if self.led_level >= 0.5 else 1.0
            offsets = flash_offsets(self.duration_s, self.flash_ms, self.flash_every_s)
            # planned before any frame is read, so that no exposure can run ahead of a flash
            flashes = self.plan.plan_flashes([self.t0_ns + int(o * 1e9) for o in offsets], int(self.flash_ms), level)
        for s in self.streams:
            s.writer.start()
            s.reader.start()
        trigger = None
        if self.rig.sync == "software-trigger":
            trigger = threading.Thread(target=self._trigger_loop, name="trigger", daemon=True)
            trigger.start()
        elif self.rig.sync == "hardware-trigger" and self.plan is not None:
            self._leds_call(self.plan.start_trigger, self.rig.fps)
        if flashes is not None:
            flashes.start()
        try:
            self._watch()
        finally:
            self.stop_ns = self.clock.now_ns()
            if self.plan is not None:
                self.plan.join()
            if trigger is not None:
                trigger.join()
            if self.rig.sync == "hardware-trigger" and self.plan is not None:
                self.plan.stop_trigger()

    def _leds_call(self, fn: Callable, *args: Any) -> None:
        from .leds import LedError

        try:
            fn(*args)
        except LedError as exc:
            self.plan.errors.append(str(exc))
            self.event("leds", "error", str(exc))

    def _watch(self) -> None:
        """The main thread: live line, end of the take, lost cameras."""
        from tqdm import tqdm

        bar = tqdm(total=round(self.duration_s, 3), desc=f"rec {self.take}", unit="s", file=sys.stderr,
                   disable=not self.progress, mininterval=0.5, dynamic_ncols=True,
                   bar_format="{desc} |{bar:16}| {n:.2f}/{total:.2f} s")
        try:
            shown = time.monotonic()
            while any(s.reader.is_alive() for s in self.streams):
                if all(s.report.status != "ok" for s in self.streams):
                    self.stop.set("every camera was lost")
                if self.stop.wait(0.05):
                    break
                if time.monotonic() - shown >= 0.5:
                    self._live(bar)
                    shown = time.monotonic()
            for s in self.streams:
                s.reader.join(JOIN_S)
                if s.reader.is_alive():
                    s.lost("failed", f"read() did not return within {JOIN_S:g} s; camera abandoned")
                    s.abandoned = True
            self._live(bar, refresh=False)   # close() draws the final state
        finally:
            bar.close()

    def _live(self, bar: Any, refresh: bool = True) -> None:
        if bar.disable:
            return
        elapsed = [((s.last_t_host or self.t0_ns) - self.t0_ns) / 1e9 for s in self.streams if s.active]
        now = max(0.0, min(min(elapsed, default=self.duration_s), self.duration_s))
        bar.n = round(now, 3)
        parts = []
        for s in self.streams:
            r = s.report
            took = max(((s.last_t_host or self.t0_ns) - self.t0_ns) / 1e9, 1e-3)
            parts.append((s.id, r.frames / took, r.seq_gaps, r.status))
        if len(parts) <= 6:
            text = " ".join(f"{i} {f:.0f}fps/{d}" + ("" if st == "ok" else f" {st}") for i, f, d, st in parts)
        else:
            fps = [p[1] for p in parts if p[3] == "ok"]
            worst = min(parts, key=lambda p: p[1])
            drops = sum(p[2] for p in parts)
            lost = [p[0] for p in parts if p[3] != "ok"]
            text = (f"{len(parts)} cams {np.mean(fps) if fps else 0:.1f} fps (min {worst[1]:.1f} {worst[0]}) "
                    f"drops {drops}" + (f" lost {','.join(lost)}" if lost else ""))
        bar.set_description_str(f"rec {self.take}: {text}", refresh=refresh)

    def _trigger_loop(self) -> None:
        """Software trigger: every camera once per nominal tick, on the take's clock."""
        period = 1e9 / self.rig.fps
        fast = is_fast(self.clock)
        k = 0
        while not self.stop.is_set():
            tick = self.t0_ns + int(round(k * period))
            if tick >= self.end_ns or not wait_until(self.clock, tick, self.stop):
                break
            pin = self.clock.pinned(tick) if fast and isinstance(self.clock, SimTakeClock) else contextlib.nullcontext()
            with pin:
                first = self.clock.now_ns()
                for s in self.streams:
                    if s.active:
                        try:
                            s.camera.trigger()
                        except Exception as exc:
                            s.lost("failed", f"trigger: {type(exc).__name__}: {exc}")
                last = self.clock.now_ns()
            self.ticks["tick"].append(k)
            self.ticks["t_sent_ns"].append(first)
            self.ticks["t_sent_last_ns"].append(last)
            k += 1
        # a fast virtual clock only moves when told: let idle readers see the end of the take
        wait_until(self.clock, self.end_ns, self.stop)

    def _close_cameras(self, opened: list[Camera]) -> None:
        for cam in opened:
            for step in (cam.stop, cam.close):
                try:
                    step()
                except Exception as exc:
                    self.event(next((s.id for s in self.streams if s.camera is cam), "?"), "close-failed", str(exc))

    # -- take.json --------------------------------------------------------------------------
    def _write_meta(self, status: str, reason: str, extra: dict[str, Any] | None = None) -> dict[str, Any]:
        rig = self.rig
        sizes = {(s.report.width, s.report.height) for s in self.streams}
        clock = self.clock
        if isinstance(clock, VirtualClock):
            clock_desc = {"kind": "virtual", "time_scale": clock.time_scale,
                          "note": "frames, ticks and t_clock_ns fields are on the simulated host clock; "
                                  "LED log t_send_ns/t_ack_ns are the host's CLOCK_MONOTONIC"}
        else:
            clock_desc = {"kind": "CLOCK_MONOTONIC"}
        meta: dict[str, Any] = {
            "version": 1, "take": self.take, "kind": self.kind, "rig": rig.name,
            "cameras": [asdict(s.report) for s in self.streams],
            "fps": rig.fps, "resolution": list(next(iter(sizes))) if len(sizes) == 1 else None,
            "sync": rig.sync, "clock": clock_desc, "duration_s": self.duration_s,
            "start_ns": self.start_ns, "t0_ns": self.t0_ns,
            "stop_ns": self.stop_ns,
            "status": status, "reason": reason, "created": self.created,
            "frames": sum(s.report.frames for s in self.streams),
            "lost_cameras": [s.id for s in self.streams if s.report.status != "ok"],
            "events": list(self.events),
            "storage": {"jpeg_quality": self.storage.jpeg_quality, "jpeg_chroma": self.storage.jpeg_chroma},
        }
        if self.backend_note:
            meta["backend_note"] = self.backend_note
        plan = self.plan
        if plan is not None:
            ctl = plan.controller
            cfg = rig.leds   # as configured ("sim" rather than the pseudo-terminal behind it)
            meta["leds"] = {"protocol": cfg.protocol if cfg else ctl.protocol, "port": cfg.port if cfg else ctl.port,
                            "panels": ctl.panels, "level": self.led_level, "errors": list(plan.errors)}
            meta["led_log"] = plan.log()
            meta["flashes"] = list(plan.flashes)
        else:
            meta["leds"], meta["led_log"], meta["flashes"] = None, [], []
        if rig.sync == "software-trigger":
            meta["triggers"] = {"source": "software", "period_ns": 1e9 / rig.fps, **self.ticks}
        elif rig.sync == "hardware-trigger":
            meta["triggers"] = {"source": "controller" if plan is not None and plan.trigger else "external",
                                "controller": plan.trigger if plan is not None else None}
        meta.update(extra or {})
        write_atomic(self.path / "take.json", json.dumps(meta, indent=1).encode())
        return meta


def _reserve(path: Path, size: int) -> None:
    """Allocate `size` bytes that the take gives back to finish its files on a full disk."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o600)
    try:
        os.posix_fallocate(fd, 0, size)
    except OSError as exc:
        os.close(fd)
        path.unlink()
        raise DiskSpaceError(f"{path.parent}: cannot reserve {size / 2**20:.0f} MB to finish the take "
                             f"({exc.strerror})") from None
    os.close(fd)


# -- one take of a session ------------------------------------------------------------------
def estimate_take_bytes(rig: RigConfig, duration_s: float) -> int:
    """Bytes a take will need: frames x (JPEG estimate + mkv and frames.csv overhead) per camera."""
    total = 0.0
    for c in rig.cameras:
        frames = c.fps * duration_s + 2
        total += frames * (JPEG_BYTES_BASE + JPEG_BYTES_PER_PIXEL * c.width * c.height + 100)
    return int(total)


def check_disk(rig: RigConfig, folder: Path, duration_s: float) -> None:
    """Refuse a take that does not fit: estimate + storage.min_free_gb + the finishing reserve."""
    probe = folder
    while not probe.exists():
        probe = probe.parent
    free = shutil.disk_usage(probe).free
    take = estimate_take_bytes(rig, duration_s)
    need = take + rig.storage.min_free_gb * 1e9 + BALLAST_BYTES
    if free < need:
        cams = len(rig.cameras)
        raise DiskSpaceError(
            f"{folder}: not enough free disk: the take needs {need / 1e9:.2f} GB ({cams} cameras x "
            f"{rig.fps:g} FPS x {duration_s:g} s ~ {take / 1e9:.2f} GB, plus storage.min_free_gb "
            f"{rig.storage.min_free_gb:g} GB kept free), {free / 1e9:.2f} GB are free")


def prepare_take_folder(path: Path, force: bool) -> None:
    """A fresh take folder; an existing take is replaced only with force."""
    if path.exists():
        if not force:
            raise RecordError(f"{path}: take exists; use --force to record it again")
        if not path.is_dir() or (any(path.iterdir()) and not (path / "take.json").exists()):
            raise RecordError(f"{path}: exists and is not a take folder; not replacing it")
        shutil.rmtree(path)
    path.mkdir(parents=True)


def open_cameras(rig: RigConfig) -> dict[str, Camera]:
    """The real (non-simulated) cameras of a rig through their backends."""
    cams: dict[str, Camera] = {}
    for c in rig.cameras:
        if c.backend == "v4l2":
            from .cameras.v4l2 import V4l2Camera
            cams[c.id] = V4l2Camera(c, sync=rig.sync)
        elif c.backend == "aravis":
            from .cameras.aravis import AravisCamera
            cams[c.id] = AravisCamera(c, sync=rig.sync)
        else:
            raise RecordError(f"{rig.source}: camera {c.id}: backend {c.backend!r} cannot be opened here")
    return cams


def record_take(rig: RigConfig, session: str | Path, take: str, kind: str, duration_s: float, *,
                force: bool = False, subject: str | None = None, operator: str | None = None,
                obj: str | None = None, leds: Any = None, use_leds: bool = True,
                level: float | None = None, flash_ms: int | None = None, flash_every_s: float = 1.0,
                flash_level: float | None = None, stop: StopFlag | None = None, progress: bool = True,
                wrap_camera: Callable[[str, Camera], Camera] | None = None,
                label_frames: Sequence[int] | None = None) -> TakeResult:
    """Record one take into SESSION/TAKE and keep session.toml up to date.

    `leds`: an LED controller already open (the protocol keeps one across takes); otherwise
    rig.leds is opened for the take when use_leds. For a simulated rig the cube renders the
    take, its lighting follows the (simulated) LED controller, and ground_truth.h5 and the
    session's tags.json are written. `wrap_camera` wraps each camera (tests inject faults).
    """
    check_take_name(take)
    check_kind(kind)
    if not duration_s > 0:
        raise RecordError(f"duration {duration_s} s: must be positive")
    if flash_ms and (not use_leds or (leds is None and rig.leds is None)):
        raise RecordError(f"{rig.source}: flashes need the LED controller ([leds] in rig.toml, without --no-leds)")
    backends = {c.backend for c in rig.cameras}
    if "sim" in backends and len(backends) > 1:
        raise RecordError(f"{rig.source}: simulated and real cameras cannot share a take (backends: "
                          f"{', '.join(sorted(backends))})")
    session_dir = Path(session)
    take_dir = session_dir / take
    if take_dir.exists() and not force:
        raise RecordError(f"{take_dir}: take exists; use --force to record it again")
    check_disk(rig, session_dir, duration_s)
    sess = open_session(session_dir, rig, subject=subject, operator=operator, obj=obj)
    stop = stop or StopFlag()
    own = leds is None and use_leds and rig.leds is not None
    if own:
        from .leds import open_led_controller
        leds = open_led_controller(rig.leds)
    controller = leds if use_leds else None
    try:
        if "sim" in backends:
            from .sim.cube import SimulatedCube

            clock: Clock = SimTakeClock(time_scale=rig.sim.time_scale)
            plan = LedPlan(controller, clock, stop) if controller is not None else None
            lighting = plan.lighting if plan is not None and plan.device is not None else None
            cube = SimulatedCube(rig, kind, duration_s, clock=clock, lighting=lighting)
            cameras: dict[str, Camera] = {c.id: cube.camera(c.id) for c in rig.cameras}
            t0: int | None = cube.t0_ns
            note = ("simulated cube: hardware-trigger pulse k fires at tick k" if rig.sync == "hardware-trigger"
                    else "simulated cube")

            def finish() -> dict[str, Any]:
                out: dict[str, Any] = {"ground_truth": None}
                try:
                    cube.write_ground_truth(take_dir / "ground_truth.h5", label_frames)
                    cube.world.write_tags(session_dir / "tags.json")
                    out["ground_truth"] = "ground_truth.h5"
                except OSError as exc:
                    out["ground_truth_error"] = str(exc)
                return out
        else:
            clock, plan, t0, note, finish = MonotonicClock(), None, None, "", None
            cameras = open_cameras(rig)
        if wrap_camera is not None:
            cameras = {k: wrap_camera(k, v) for k, v in cameras.items()}
        prepare_take_folder(take_dir, force)
        sess.update_take(take, kind=kind, status="recording", reason="", started=utc_now(), duration_s=duration_s)
        recorder = Recorder(rig, take_dir, kind, duration_s, cameras, clock, take=take, t0_ns=t0,
                            leds=controller, plan=plan, level=level, flash_ms=flash_ms,
                            flash_every_s=flash_every_s, flash_level=flash_level, stop=stop,
                            progress=progress, backend_note=note, on_stop=finish)
        try:
            result = recorder.run()
        except BaseException as exc:
            sess.update_take(take, status="interrupted", reason=f"{type(exc).__name__}: {exc}")
            raise
    finally:
        if own:
            leds.close()
    sess.update_take(take, status=result.status, reason=result.reason, frames=result.frames,
                     lost_cameras=[c.id for c in result.lost])
    return result
