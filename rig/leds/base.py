"""What every LED controller shares: a serial link that survives an unplug, the command log and
the absolute set-point that is re-applied after a reconnect."""

from __future__ import annotations

import copy
import select
import termios
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import serial

from manus_core.errors import LedDisconnected, LedError, LedValueError, LinkLost


def now_ns() -> int:
    """Host time of the log: CLOCK_MONOTONIC in ns, the clock of every other timestamp of a take."""
    return time.clock_gettime_ns(time.CLOCK_MONOTONIC)


@dataclass(frozen=True)
class Backoff:
    """Reconnect schedule: waits of initial_s, initial_s*factor, ... capped at max_s, for give_up_s in all."""

    initial_s: float = 0.05
    factor: float = 2.0
    max_s: float = 1.0
    give_up_s: float = 10.0


DEFAULT_BACKOFF = Backoff()

# How a port is opened: pyserial's constructor, or a wrapper that sees every (re)open attempt,
# with which a test plugs a simulated device back in at a chosen attempt rather than after a delay.
Opener = Callable[..., serial.Serial]


class CommandLog:
    """Every command and link event with host times; records() is ready for take.json."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._records: list[dict[str, Any]] = []

    def add(self, record: dict[str, Any]) -> dict[str, Any]:
        with self._lock:
            self._records.append(record)
        return record

    def event(self, name: str, **fields: Any) -> dict[str, Any]:
        return self.add({"event": name, "t_ns": now_ns(), **fields})

    def records(self) -> list[dict[str, Any]]:
        with self._lock:
            return copy.deepcopy(self._records)


class SerialLink:
    """A pyserial port, reopened with exponential backoff when the device disappears.

    A USB controller that is unplugged and plugged back keeps its /dev/serial/by-id name but
    is a new device, so the port is closed and opened again by name rather than retried in place.
    """

    def __init__(self, port: str, baudrate: int, backoff: Backoff, log: CommandLog,
                 opener: Opener = serial.Serial) -> None:
        self.port = port
        self.baudrate = baudrate
        self.backoff = backoff
        self._log = log
        self._opener = opener
        self._ser: serial.Serial | None = None

    def open(self) -> None:
        try:
            self._ser = self._open_once()
        except (OSError, ValueError) as exc:
            raise LedError(f"LED controller on {self.port}: cannot open ({exc})") from None

    def _open_once(self) -> serial.Serial:
        # exclusive: a second process writing to the same controller would interleave frames.
        return self._opener(self.port, self.baudrate, timeout=0, write_timeout=1.0, exclusive=True)

    def write(self, data: bytes) -> None:
        if self._ser is None:
            raise LinkLost("port closed")
        try:
            self._ser.write(data)
            self._ser.flush()
        except (OSError, serial.SerialException, termios.error) as exc:
            raise LinkLost(str(exc)) from exc

    def read(self, timeout_s: float) -> bytes:
        """Whatever arrives within timeout_s (at least one byte unless it times out)."""
        if self._ser is None:
            raise LinkLost("port closed")
        try:
            # select rather than pyserial's timeout, whose setter reconfigures the port each time.
            if not select.select([self._ser.fileno()], [], [], max(timeout_s, 0.0))[0]:
                return b""
            return self._ser.read(max(1, self._ser.in_waiting))
        except (OSError, serial.SerialException, termios.error) as exc:
            raise LinkLost(str(exc)) from exc

    def drain_input(self) -> bytes:
        return self.read(0.0)

    def reconnect(self, reason: str) -> None:
        """Close, then reopen by name with backoff; raise LedDisconnected when the budget is spent."""
        self.close()
        t_lost = now_ns()
        wait = self.backoff.initial_s
        attempts = 0
        deadline = time.monotonic() + self.backoff.give_up_s
        last_error = reason
        while True:
            attempts += 1
            try:
                self._ser = self._open_once()
            except (OSError, ValueError) as exc:
                last_error = str(exc)
            else:
                self._log.event("reconnect", port=self.port, attempts=attempts, reason=reason,
                                downtime_ms=round((now_ns() - t_lost) / 1e6, 3))
                return
            if time.monotonic() + wait > deadline:
                self._log.event("disconnected", port=self.port, attempts=attempts, reason=last_error)
                raise LedDisconnected(
                    f"LED controller on {self.port}: disconnected ({reason}) and not back after "
                    f"{self.backoff.give_up_s:g} s ({attempts} attempts; last: {last_error})")
            time.sleep(wait)
            wait = min(wait * self.backoff.factor, self.backoff.max_s)

    def close(self) -> None:
        if self._ser is not None:
            try:
                self._ser.close()
            except OSError:
                pass
            self._ser = None


def check_level(level: float) -> float:
    if not 0.0 <= float(level) <= 1.0:
        raise LedValueError(f"LED level {level!r} is outside 0..1")
    return float(level)


class LedController:
    """The common surface of the ASCII and DMX controllers.

    Levels are absolute set-points (0..1 per panel); the controller remembers the last one it
    was asked for and puts it back after the device reconnects, so repeating a command is
    always safe.
    """

    protocol = "none"

    def __init__(self, port: str, panels: int, default_level: float) -> None:
        if panels < 1:
            raise LedValueError(f"LED controller on {port}: panels must be at least 1, got {panels}")
        self.port = port
        self.panels = panels
        self.default_level = check_level(default_level)
        self.log = CommandLog()
        self._levels = [0.0] * panels
        self._owned: list[Any] = []

    @property
    def levels(self) -> tuple[float, ...]:
        """The current set-point (what the panels show outside a flash)."""
        return tuple(self._levels)

    def own(self, resource: Any) -> None:
        """Close `resource` (e.g. a simulated device) together with this controller."""
        self._owned.append(resource)

    def _check_panel(self, panel: int) -> int:
        if not 0 <= panel < self.panels:
            raise LedValueError(f"LED panel {panel} does not exist (panels 0..{self.panels - 1})")
        return panel

    def set_levels(self, levels: Sequence[float]) -> dict[str, Any]:
        """Set every panel at once; returns the log record of the command."""
        if len(levels) != self.panels:
            raise LedValueError(f"expected {self.panels} LED levels, got {len(levels)}")
        return self._apply([check_level(x) for x in levels])

    def set_panel(self, panel: int, level: float) -> dict[str, Any]:
        new = list(self._levels)
        new[self._check_panel(panel)] = check_level(level)
        return self._apply(new)

    def on(self, level: float | None = None) -> dict[str, Any]:
        return self._apply([check_level(self.default_level if level is None else level)] * self.panels)

    def off(self) -> dict[str, Any]:
        return self._apply([0.0] * self.panels)

    def records(self) -> list[dict[str, Any]]:
        """The command log with host CLOCK_MONOTONIC times, JSON-ready for take.json."""
        return self.log.records()

    def _apply(self, levels: list[float]) -> dict[str, Any]:
        raise NotImplementedError

    def flash(self, ms: int, level: float = 1.0) -> dict[str, Any]:
        raise NotImplementedError

    def trigger(self, rate_hz: float, count: int = 0, width_us: int = 100) -> dict[str, Any]:
        raise NotImplementedError

    def stop_trigger(self) -> dict[str, Any]:
        raise NotImplementedError

    def status(self) -> dict[str, Any]:
        raise NotImplementedError

    def close(self) -> None:
        for resource in reversed(self._owned):
            resource.close()
        self._owned.clear()

    def __enter__(self) -> LedController:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
