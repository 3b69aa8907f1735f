"""What a take delivered: per camera (take.json "cameras") and as a whole."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


@dataclass
class CameraReport:
    """What one camera delivered in a take (take.json "cameras").

    Not frozen: the camera's reader and writer threads count into it while the take runs.
    """

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


@dataclass(frozen=True)
class TakeResult:
    path: Path
    status: str               # complete | interrupted
    reason: str
    by_signal: bool
    cameras: list[CameraReport]
    meta: dict[str, Any] = field(default_factory=dict)
    # The LED controller over the take (LedPlan.status): off (none), ok,
    # lost (disconnected and not back) or failed (a command timed out, was refused or went stale).
    leds: str = "off"

    @property
    def frames(self) -> int:
        return sum(c.frames for c in self.cameras)

    @property
    def lost(self) -> list[CameraReport]:
        return [c for c in self.cameras if c.status != "ok"]

    @property
    def led_errors(self) -> list[str]:
        """What failed on the LED controller during the take (take.json leds.errors)."""
        return list((self.meta.get("leds") or {}).get("errors", []))

    @property
    def exit_code(self) -> int:
        """0 complete with every camera and the LEDs; 130 stopped by a signal; 1 any other fault
        (a lost camera or LED controller: the frames are kept, the take is not what was asked)."""
        if self.status == "interrupted" and self.by_signal:
            return 130
        return 1 if self.status == "interrupted" or self.lost or self.leds in ("lost", "failed") else 0
