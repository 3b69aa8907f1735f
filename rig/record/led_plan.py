"""The take's LED commands: the level, the flashes of the optical sync check and the trigger,
placed on the take's clock, and the lighting they give the simulated cube."""

from __future__ import annotations

import bisect
import contextlib
import math
import threading
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from manus_core.errors import LedDisconnected, LedError

from ..clock import Clock, VirtualClock, is_fast
from ..leds import LedController
from .stop import StopFlag, wait_until


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

    def __init__(self, controller: LedController, clock: Clock, stop: StopFlag) -> None:
        self.controller = controller
        self.clock = clock
        self.stop = stop
        self.virtual = isinstance(clock, VirtualClock)
        self.fast = is_fast(clock)
        self.device = getattr(controller, "sim", None)   # the simulated controller, if it is one
        self.flashes: list[dict[str, Any]] = []
        self.errors: list[str] = []
        self.lost = False   # the controller went away mid-take and did not come back
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
            self._failed("flash", exc)
        finally:
            self.cancel()

    def _failed(self, what: str, exc: LedError) -> None:
        self.errors.append(f"{what}: {exc}")
        self.lost |= isinstance(exc, LedDisconnected)

    @property
    def status(self) -> str:
        """The controller over the take: ok; lost (disconnected and not back); failed (a command
        timed out, was refused or answered with a stale reply)."""
        return "lost" if self.lost else "failed" if self.errors else "ok"

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
        try:
            record = self.controller.trigger(rate_hz)
        except LedDisconnected:
            self.lost = True
            raise
        reply = record.get("reply", {})
        self.trigger = {"rate_hz": rate_hz, "seq": record.get("seq"), "t_clock_ns": self.to_clock(record["t_send_ns"]),
                        "p0": int(reply["p0"]) if "p0" in reply else None,
                        "t0_controller_us": int(reply["t0"]) if "t0" in reply else None}

    def stop_trigger(self) -> None:
        if self.lost:
            # its outputs went with it, and another reconnect would hold up the end of the take
            return
        try:
            status = self.controller.status()
            self.controller.stop_trigger()
        except LedError as exc:
            self._failed("stop trigger", exc)
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
