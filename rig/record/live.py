"""What a take looks like while it records, for a monitor (manus_capture.monitor's MonitorSource,
by method names only: camera_ids, snapshot, latest_jpeg).

Nothing here takes a lock that a reader or writer holds: the counters are the CameraReport fields
the writers update (plain ints, read under the GIL), the ring fill is the length of the ring's
deque, and the latest JPEG is the reference a writer assigns after storing a batch. A snapshot
costs a few attribute reads per camera; the free disk space is asked at most every DISK_POLL_S.

    {"take", "session", "kind", "status": "waiting"|"recording"|"complete"|"interrupted",
     "t_ns" (host CLOCK_MONOTONIC now), "elapsed_s" (on the take's clock), "duration_s",
     "cameras": [{"id", "frames", "drops", "bytes", "buffer_fill", "status", "last_frame_ns"}],
     "disk": {"path", "free_bytes", "written_bytes", "min_free_gb"},
     "leds": None | {"level", "status", "flashes"},
     "session_progress" (LiveSession only): {"done", "total", "last_take", "last_verdict"}}
"""

from __future__ import annotations

import contextlib
import time
from pathlib import Path
from typing import Any, Protocol

from manus_core.rig_config import RigConfig

from ..clock import Clock
from .disk import free_bytes
from .led_plan import LedPlan
from .streams import Stream

DISK_POLL_S = 0.25            # free space is asked of the file system at most this often


class LiveTake(Protocol):
    """What a Live reads of its take (the Recorder)."""

    rig: RigConfig
    path: Path
    take: str
    kind: str
    duration_s: float
    clock: Clock
    streams: list[Stream]
    plan: LedPlan | None
    t0_ns: int | None
    start_ns: int | None
    stop_ns: int | None

    @property
    def led_level(self) -> float: ...


class DiskProbe:
    """Free space of a folder's disk, asked at most every DISK_POLL_S (snapshots may come often)."""

    def __init__(self, folder: Path, min_free_gb: float) -> None:
        self.folder, self.min_free_gb = folder, min_free_gb
        self._free: int | None = None
        self._asked = -DISK_POLL_S

    def reading(self, written_bytes: int) -> dict[str, Any]:
        now = time.monotonic()
        if now - self._asked >= DISK_POLL_S:
            self._asked = now
            with contextlib.suppress(OSError):   # a vanished mount reads as the last value seen
                self._free = free_bytes(self.folder)
        return {"path": str(self.folder), "free_bytes": self._free, "written_bytes": written_bytes,
                "min_free_gb": self.min_free_gb}


class Live:
    """One take as it records (Recorder.live); stays valid after the take with its final counters."""

    def __init__(self, rec: LiveTake) -> None:
        self._rec = rec
        self._streams = {s.id: s for s in rec.streams}
        self._disk = DiskProbe(rec.path.parent, rec.rig.storage.min_free_gb)
        self.status = "recording"   # the Recorder sets complete or interrupted when the take ends

    def camera_ids(self) -> list[str]:
        return list(self._streams)

    def latest_jpeg(self, cam: str) -> bytes | None:
        """The JPEG bytes of `cam`'s latest stored frame (None before its first); KeyError if unknown."""
        latest = self._streams[cam].latest
        return None if latest is None else latest[0]

    def snapshot(self) -> dict[str, Any]:
        rec = self._rec
        cameras = []
        for s in self._streams.values():
            r, latest = s.report, s.latest
            cameras.append({"id": s.id, "frames": r.frames, "drops": r.seq_gaps, "bytes": r.bytes,
                            "buffer_fill": s.fill, "status": r.status,
                            "last_frame_ns": None if latest is None else latest[1]})
        elapsed = 0.0
        if rec.t0_ns is not None and rec.start_ns is not None:
            now = rec.stop_ns if rec.stop_ns is not None else rec.clock.now_ns()
            elapsed = min(max(0.0, (now - rec.t0_ns) / 1e9), rec.duration_s)
        plan = rec.plan
        leds = None if plan is None else {"level": rec.led_level, "status": plan.status, "flashes": len(plan.flashes)}
        return {"take": rec.take, "session": rec.path.parent.name, "kind": rec.kind, "status": self.status,
                "t_ns": time.monotonic_ns(), "elapsed_s": elapsed, "duration_s": rec.duration_s,
                "cameras": cameras, "disk": self._disk.reading(sum(c["bytes"] for c in cameras)), "leds": leds}


class LiveSession:
    """A session as a monitor sees it across takes (`record` has a session of one take).

    record_take(..., on_live=session.attach) hands it each take's Live before the take starts;
    while it records, and between takes, the snapshot is that take's (final counters once it
    ended), plus session_progress, which the command updates with finished(). Before the first
    take: status "waiting", every camera of the rig at zero.
    """

    def __init__(self, rig: RigConfig, session_dir: Path, total: int = 1) -> None:
        self._ids = [c.id for c in rig.cameras]
        self._session = Path(session_dir)
        self._disk = DiskProbe(self._session, rig.storage.min_free_gb)
        self.live: Live | None = None
        self._progress: dict[str, Any] = {"done": 0, "total": total, "last_take": None, "last_verdict": None}

    def attach(self, live: Live) -> None:
        self.live = live

    def finished(self, take: str, verdict: str | None, done: int) -> None:
        """A take ended: `done` takes of the session are complete; `verdict` of its sync check
        (pass, fail, error; None when not checked)."""
        self._progress = {**self._progress, "done": done, "last_take": take, "last_verdict": verdict}

    def camera_ids(self) -> list[str]:
        live = self.live
        return live.camera_ids() if live is not None else list(self._ids)

    def latest_jpeg(self, cam: str) -> bytes | None:
        live = self.live
        if live is not None:
            return live.latest_jpeg(cam)
        if cam not in self._ids:
            raise KeyError(cam)
        return None

    def snapshot(self) -> dict[str, Any]:
        live = self.live
        snap = live.snapshot() if live is not None else self._waiting()
        snap["session_progress"] = dict(self._progress)
        return snap

    def _waiting(self) -> dict[str, Any]:
        cameras = [{"id": cam, "frames": 0, "drops": 0, "bytes": 0, "buffer_fill": 0.0, "status": "ok",
                    "last_frame_ns": None} for cam in self._ids]
        return {"take": None, "session": self._session.name, "kind": None, "status": "waiting",
                "t_ns": time.monotonic_ns(), "elapsed_s": 0.0, "duration_s": None, "cameras": cameras,
                "disk": self._disk.reading(0), "leds": None}
