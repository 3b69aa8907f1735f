"""What the monitor shows: the `MonitorSource` protocol.

Structural (a `typing.Protocol`), so the recorder in `rig` can be a source without importing the
application layer. The live snapshot a recorder gives is a plain dict of cumulative counters:

    {"take", "session", "kind", "status": "recording"|"complete"|"interrupted",
     "t_ns" (host CLOCK_MONOTONIC now), "elapsed_s", "duration_s",
     "cameras": [{"id", "frames", "drops", "bytes", "buffer_fill", "status", "last_frame_ns"}],
     "disk": {"path", "free_bytes", "written_bytes", "min_free_gb"},
     "leds": None | {"level", "status", "flashes"},
     "session_progress" (optional): {"done", "total", "last_take", "last_verdict"}}

The server derives rates (fps, bytes/s, disk write rate) and alerts from successive snapshots;
a source only counts.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable


@runtime_checkable
class MonitorSource(Protocol):
    """A live recording or a recorded take/session, as the monitor reads it."""

    def camera_ids(self) -> list[str]:
        """The cameras, in display order."""
        ...

    def snapshot(self) -> dict:
        """Cumulative counters now (the dict described in this module's docstring)."""
        ...

    def latest_jpeg(self, cam: str) -> bytes | None:
        """The JPEG bytes of camera `cam`'s latest frame, None before its first; KeyError if unknown."""
        ...
