"""The recorder: every camera of a take into one take folder (DESIGN.md, "On disk"; stage 1).

    reader thread per camera --(bounded ring)--> writer thread per camera --> cams/CAM.mkv
                                                                        \\--> frames.csv (shared)

(rig.record.streams). Every file stays readable if the process dies (see rig/mkv.py); an orderly
stop (end of the duration, Ctrl-C, SIGTERM, a full disk, a failing writer) finishes every file
and writes take.json with the status and the reason.

Time: one clock per take. Real rigs use CLOCK_MONOTONIC; the simulated rig its virtual clock, on
which every frame, tick and LED event of the take is expressed (take.json says which).
"""

from __future__ import annotations

import contextlib
import json
import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

from manus_core.errors import LedError
from manus_core.fileio import write_atomic
from manus_core.frames_csv import FILE_NAME as FRAMES_CSV
from manus_core.progress import Progress, silent
from manus_core.rig_config import RigConfig
from manus_core.session import check_kind, utc_now
from manus_core.take import recorder_identity

from ..cameras import Camera, TakeCameras
from ..clock import Clock, SimTakeClock, VirtualClock, is_fast
from ..mkv import MkvWriter
from .disk import BALLAST_BYTES, RESERVE_NAME, reserve
from .led_plan import LedPlan, flash_offsets
from .live import Live
from .options import RecordOptions
from .report import CameraReport, TakeResult
from .stop import StopFlag, wait_until
from .streams import FrameCsv, Stream

REAL_LEAD_NS = 50_000_000     # real rigs: tick 0 comes this long after the cameras started
JOIN_S = 10.0                 # a reader whose read() never returns is abandoned after this
RING_S = 0.5                  # frames a camera's ring holds, in seconds of its frame rate
PROGRESS_S = 0.5              # how often the take reports its progress


class Recorder:
    """Record `cameras` (opened here) into the take folder `path` for duration_s on `clock`.

    cameras.t0_ns is the take's tick 0 (the sim cube's; for real rigs REAL_LEAD_NS after the
    cameras start); the take ends at t0 + duration; cameras.finish runs after the cameras are
    closed and returns extra take.json fields. `plan` is the take's LedPlan (made with the same
    clock and StopFlag), or None without LEDs. progress("rec TAKE", frames stored, frames
    expected) is reported every PROGRESS_S. `live` (rig.record.live.Live) shows the take to a
    monitor from any thread, before, during and after run().
    """

    def __init__(self, rig: RigConfig, path: str | Path, kind: str, duration_s: float, cameras: TakeCameras,
                 clock: Clock, *, options: RecordOptions = RecordOptions(), plan: LedPlan | None = None,
                 stop: StopFlag | None = None, progress: Progress = silent) -> None:
        self.rig, self.path, self.kind = rig, Path(path), check_kind(kind)
        self.take = self.path.name
        self.duration_s = float(duration_s)
        self.clock = clock
        self.stop = stop or StopFlag()
        self.plan = plan
        self.options = options
        self.progress = progress
        self.storage = rig.storage
        self.jpeg_params = rig.storage.jpeg_params()
        self.backend_note = cameras.note
        self.on_stop = cameras.finish
        self.t0_ns = cameras.t0_ns
        self.end_ns = sys.maxsize
        self.events: list[dict[str, Any]] = []
        self._events_lock = threading.Lock()
        self.ticks: dict[str, list[int]] = {"tick": [], "t_sent_ns": [], "t_sent_last_ns": []}
        configs = {c.id: c for c in rig.cameras}
        self.streams: list[Stream] = []
        for cam_id, camera in cameras.cameras.items():
            c = configs[cam_id]
            # the sync stage needs the transfer latency floor to tell it from a clock offset; the
            # simulated cameras declare theirs in rig.toml
            report = CameraReport(cam_id, c.backend, c.width, c.height, c.fps, c.pixel_format, c.exposure_us,
                                  c.sim.latency_ms if c.sim is not None else None)
            self.streams.append(Stream(self, cam_id, camera, report, max(8, math.ceil(c.fps * RING_S))))
        self.expected_frames = round(sum(s.report.fps for s in self.streams) * self.duration_s)
        self.csv: FrameCsv | None = None
        self.start_ns: int | None = None
        self.stop_ns: int | None = None
        self.created = utc_now()
        self.live = Live(self)

    @property
    def led_level(self) -> float:
        """The take's LED set-point: --level, else the controller's default ([leds] level)."""
        level = self.options.level
        return level if level is not None else self.plan.controller.default_level

    def event(self, cam: str, what: str, message: str) -> None:
        with self._events_lock:
            self.events.append({"t_ns": self.clock.now_ns(), "cam": cam, "event": what, "message": message})

    # -- the take ---------------------------------------------------------------------------
    def run(self) -> TakeResult:
        """Open, stream, stop, finish; always leaves a readable take folder behind."""
        (self.path / "cams").mkdir(parents=True, exist_ok=True)
        ballast = self.path / RESERVE_NAME
        reserve(ballast, BALLAST_BYTES)
        self.csv = FrameCsv(self.path / FRAMES_CSV)
        self._write_meta("recording", "")
        opened: list[Camera] = []
        try:
            for s in self.streams:
                s.camera.open()
                opened.append(s.camera)
                s.camera.configure()
                self._describe(s)
                r = s.report
                s.mkv = MkvWriter(self.path / "cams" / f"{s.id}.mkv", r.width, r.height, r.fps, name=s.id)
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
                self.live.status = "interrupted"
                with contextlib.suppress(Exception):
                    self._write_meta("interrupted", self.stop.reason)
        status = "interrupted" if self.stop.is_set() else "complete"
        extra = self.on_stop() if self.on_stop is not None else {}
        meta = self._write_meta(status, self.stop.reason, extra)
        self.live.status = status
        return TakeResult(self.path, status, self.stop.reason, self.stop.by_signal,
                          [s.report for s in self.streams], meta, self.plan.status if self.plan is not None else "off")

    def _describe(self, s: Stream) -> None:
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
        flash_ms = self.options.flash_ms
        if self.plan is not None and flash_ms:
            level = self.options.flash_level
            if level is None:   # most contrast against the set-point
                level = 0.0 if self.led_level >= 0.5 else 1.0
            offsets = flash_offsets(self.duration_s, flash_ms, self.options.flash_every_s)
            # planned before any frame is read, so that no exposure can run ahead of a flash
            flashes = self.plan.plan_flashes([self.t0_ns + int(o * 1e9) for o in offsets], int(flash_ms), level)
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
        try:
            fn(*args)
        except LedError as exc:
            self.plan.errors.append(str(exc))
            self.event("leds", "error", str(exc))

    def _watch(self) -> None:
        """The main thread: progress, end of the take, lost cameras."""
        shown = time.monotonic()
        while any(s.reader.is_alive() for s in self.streams):
            if all(s.report.status != "ok" for s in self.streams):
                self.stop.set("every camera was lost")
            if self.stop.wait(0.05):
                break
            if time.monotonic() - shown >= PROGRESS_S:
                self._report_progress()
                shown = time.monotonic()
        for s in self.streams:
            s.reader.join(JOIN_S)
            if s.reader.is_alive():
                s.lost("failed", f"read() did not return within {JOIN_S:g} s; camera abandoned")
                s.abandoned = True
        self._report_progress()

    def _report_progress(self) -> None:
        stored = sum(s.report.frames for s in self.streams)
        self.progress(f"rec {self.take}", min(stored, self.expected_frames), self.expected_frames)

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
            "status": status, "reason": reason, "created": self.created, "recorder": recorder_identity(),
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
                            "panels": ctl.panels, "level": self.led_level, "status": plan.status,
                            "errors": list(plan.errors)}
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
