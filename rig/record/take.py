"""One take of a session: the checks before it, the cameras through their backends, the LEDs,
session.toml kept up to date."""

from __future__ import annotations

import dataclasses
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

from manus_core.errors import RecordError
from manus_core.progress import Progress, silent
from manus_core.rig_config import RigConfig
from manus_core.session import check_kind, check_take_name, open_session, utc_now

from ..backends import BACKENDS
from ..cameras import Backend, TakeCameras, TakeSetup
from ..clock import Clock, MonotonicClock
from ..leds import LedController, open_led_controller
from .disk import check_disk
from .led_plan import LedPlan
from .live import Live
from .options import RecordOptions
from .recorder import Recorder
from .report import TakeResult
from .stop import StopFlag


def prepare_take_folder(path: Path, force: bool) -> None:
    """A fresh take folder; an existing take is replaced only with force."""
    if path.exists():
        if not force:
            raise RecordError(f"{path}: take exists; use --force to record it again")
        if not path.is_dir() or (any(path.iterdir()) and not (path / "take.json").exists()):
            raise RecordError(f"{path}: exists and is not a take folder; not replacing it")
        shutil.rmtree(path)
    path.mkdir(parents=True)


def rig_backends(rig: RigConfig) -> dict[str, Backend]:
    """The registered backends of the rig's cameras, in order of first use.

    A backend with a clock of its own (the simulator) takes a whole take: its cameras' times
    cannot be put on one clock with anyone else's.
    """
    backends: dict[str, Backend] = {}
    for c in rig.cameras:
        backend = BACKENDS.get(c.backend)
        if backend is None:
            raise RecordError(f"{rig.source}: camera {c.id}: backend {c.backend!r} cannot be opened here")
        backends[c.backend] = backend
    if len(backends) > 1 and any(b.clock is not None for b in backends.values()):
        raise RecordError(f"{rig.source}: simulated and real cameras cannot share a take (backends: "
                          f"{', '.join(sorted(backends))})")
    return backends


def take_clock(rig: RigConfig, backends: dict[str, Backend]) -> Clock:
    """The take's one clock: its backend's own, else the host's CLOCK_MONOTONIC."""
    own = [b.clock for b in backends.values() if b.clock is not None]
    return own[0](rig) if own else MonotonicClock()


def open_backends(backends: dict[str, Backend], setup: TakeSetup) -> TakeCameras:
    """The take's cameras (setup.cameras), each from its backend, in rig.toml order."""
    parts = [b.open(dataclasses.replace(setup, cameras=tuple(c for c in setup.cameras if c.backend == name)))
             for name, b in backends.items()]
    cameras = {cam_id: cam for part in parts for cam_id, cam in part.cameras.items()}
    finishes = [p.finish for p in parts if p.finish is not None]

    def finish() -> dict[str, Any]:
        return {k: v for f in finishes for k, v in f().items()}

    return TakeCameras({c.id: cameras[c.id] for c in setup.cameras},
                       t0_ns=next((p.t0_ns for p in parts if p.t0_ns is not None), None),
                       note="; ".join(p.note for p in parts if p.note), finish=finish if finishes else None)


def record_take(rig: RigConfig, session: str | Path, take: str, kind: str, duration_s: float,
                options: RecordOptions = RecordOptions(), *, leds: LedController | None = None,
                stop: StopFlag | None = None, progress: Progress = silent,
                on_live: Callable[[Live], None] | None = None) -> TakeResult:
    """Record one take into SESSION/TAKE and keep session.toml up to date.

    `leds`: an LED controller already open (the protocol keeps one across takes); otherwise
    rig.leds is opened for the take when options.use_leds. For a simulated rig the cube renders
    the take, its lighting follows the (simulated) LED controller, and ground_truth.h5 and the
    session's tags.json are written. `stop` ends the take early (signal handlers set it).
    `on_live` gets the take's Live (rig.record.live) before any camera opens; it stays readable
    after the take (a monitor serves it: LiveSession.attach). The sync check is not run here.
    """
    check_take_name(take)
    check_kind(kind)
    if not duration_s > 0:
        raise RecordError(f"duration {duration_s} s: must be positive")
    if options.flash_ms and (not options.use_leds or (leds is None and rig.leds is None)):
        raise RecordError(f"{rig.source}: flashes need the LED controller ([leds] in rig.toml, without --no-leds)")
    backends = rig_backends(rig)
    session_dir = Path(session)
    take_dir = session_dir / take
    if take_dir.exists() and not options.force:
        raise RecordError(f"{take_dir}: take exists; use --force to record it again")
    check_disk(rig, session_dir, duration_s)
    sess = open_session(session_dir, rig, subject=options.subject, operator=options.operator, obj=options.obj)
    stop = stop or StopFlag()
    own = leds is None and options.use_leds and rig.leds is not None
    if own:
        leds = open_led_controller(rig.leds)
    controller = leds if options.use_leds else None
    try:
        clock = take_clock(rig, backends)
        plan = LedPlan(controller, clock, stop) if controller is not None else None
        lighting = plan.lighting if plan is not None and plan.device is not None else None
        setup = TakeSetup(rig, rig.cameras, kind, duration_s, clock, take_dir, lighting, options.label_frames)
        cameras = open_backends(backends, setup)
        prepare_take_folder(take_dir, options.force)
        sess.update_take(take, kind=kind, status="recording", reason="", started=utc_now(), duration_s=duration_s)
        recorder = Recorder(rig, take_dir, kind, duration_s, cameras, clock, options=options, plan=plan, stop=stop,
                            progress=progress)
        if on_live is not None:
            on_live(recorder.live)
        try:
            result = recorder.run()
        except BaseException as exc:
            sess.update_take(take, status="interrupted", reason=f"{type(exc).__name__}: {exc}")
            raise
    finally:
        if own:
            leds.close()
    sess.update_take(take, status=result.status, reason=result.reason, frames=result.frames,
                     lost_cameras=[c.id for c in result.lost], leds=result.leds)
    return result
