"""Why a take ends before its duration, and waits on the take's clock that a stop cuts short."""

from __future__ import annotations

import threading

from ..clock import Clock, is_fast


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
