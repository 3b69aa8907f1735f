"""Host clocks. Real rigs use CLOCK_MONOTONIC; the simulated rig runs on a virtual clock that can
go faster than real time (so a 53-camera take renders on a laptop) or follow it at any scale."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator
from typing import Protocol


class Clock(Protocol):
    def now_ns(self) -> int: ...

    def sleep_until_ns(self, t_ns: int) -> None: ...


class MonotonicClock:
    """The host's CLOCK_MONOTONIC."""

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def sleep_until_ns(self, t_ns: int) -> None:
        delay = (t_ns - time.monotonic_ns()) / 1e9
        if delay > 0:
            time.sleep(delay)


class VirtualClock:
    """Simulated host time starting at `start_ns`.

    time_scale > 0: virtual time follows the real monotonic clock at that rate (1 = real time).
    time_scale == 0: virtual time only moves when someone waits for a later time or reports one
    (`advance_to`), so the simulation runs as fast as the renderer allows.
    """

    def __init__(self, start_ns: int | None = None, time_scale: float = 0.0) -> None:
        if time_scale < 0:
            raise ValueError("time_scale must be >= 0")
        self.start_ns = time.monotonic_ns() if start_ns is None else int(start_ns)
        self.time_scale = time_scale
        self._real0 = time.monotonic_ns()
        self._now = self.start_ns
        self._lock = threading.Lock()

    def now_ns(self) -> int:
        if self.time_scale > 0:
            return self.start_ns + int((time.monotonic_ns() - self._real0) * self.time_scale)
        with self._lock:
            return self._now

    def advance_to(self, t_ns: int) -> None:
        if self.time_scale == 0:
            with self._lock:
                self._now = max(self._now, int(t_ns))

    def sleep_until_ns(self, t_ns: int) -> None:
        if self.time_scale > 0:
            delay = (t_ns - self.now_ns()) / 1e9 / self.time_scale
            if delay > 0:
                time.sleep(delay)
        else:
            self.advance_to(t_ns)


def is_fast(clock: Clock) -> bool:
    """A virtual clock at time_scale 0: time moves only when the simulation reports it."""
    return isinstance(clock, VirtualClock) and clock.time_scale == 0


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
