"""A simulated LED/trigger controller: the device side of docs/leds-protocol.md on a real pty.

It behaves as the reference firmware should (HELLO sessions, dedupe of repeated sequence
numbers, controller clock, flashes timed by the controller, trigger pulses, BOOT event) and keeps
a timeline of what the panels showed, so the simulated cube can light its frames from
`state_at`. Faults of the line and of the device can be switched on for tests: unplug/replug,
reboot, silence, corrupted or torn replies, lost requests, injected garbage, and firmware that
gets sessions wrong.
"""

from __future__ import annotations

import os
import queue
import select
import tempfile
import threading
import time
import tty
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .base import now_ns
from .protocol import CACHED, LEVEL_MAX, FrameParser, Message, ParserStats, encode, from_wire, to_wire

FIRMWARE = "sim-1"
DEDUPE_DEPTH = 8


@dataclass
class _TriggerRun:
    t0_ns: int           # host time of the first pulse
    period_ns: float     # host-clock period (the controller's crystal drifts)
    count: int           # 0: until stopped
    id0: int             # id of the first pulse (ids count from boot)
    t_stop_ns: int | None = None

    def n_pulses(self, t_ns: int) -> int:
        """Pulses emitted up to and including t_ns."""
        end = t_ns if self.t_stop_ns is None else min(t_ns, self.t_stop_ns - 1)
        if end < self.t0_ns:
            return 0
        n = int((end - self.t0_ns) // self.period_ns) + 1
        return min(n, self.count) if self.count else n


class VirtualPort:
    """The device end of a virtual USB serial port: a pseudo-terminal under a stable name.

    `path` is a symlink (like /dev/serial/by-id/...) that keeps its name across unplug and
    replug while the pty behind it changes, as a USB device's by-id name does.
    """

    def __init__(self, path: str) -> None:
        self.path = path
        self.master: int | None = None
        self._slave: int | None = None

    def plug(self) -> None:
        master, slave = os.openpty()
        # Raw before any byte flows (a fresh pty echoes); the device keeps its own slave fd so
        # the master never sees a hangup while the host closes and reopens the port.
        tty.setraw(slave)
        self.master, self._slave = master, slave
        tmp_link = self.path + ".new"
        if os.path.lexists(tmp_link):
            os.unlink(tmp_link)
        os.symlink(os.ttyname(slave), tmp_link)
        os.replace(tmp_link, self.path)

    def unplug(self) -> None:
        """The port vanishes: the name goes away and the host's open file fails with EIO."""
        if self.master is None:
            return
        if os.path.lexists(self.path):
            os.unlink(self.path)
        os.close(self.master)
        os.close(self._slave)
        self.master = self._slave = None


class SimulatedLedController:
    """Serve the ASCII protocol on a VirtualPort; `path` is what a client opens."""

    def __init__(self, panels: int = 6, *, link_dir: str | Path | None = None,
                 drift_ppm: float = 0.0) -> None:
        self.panels = panels
        self.drift_ppm = drift_ppm
        self._tmp = None if link_dir else tempfile.TemporaryDirectory(prefix="leds-sim-")
        self._port = VirtualPort(str(Path(link_dir or self._tmp.name) / "ttyLEDSIM"))
        self.path = self._port.path
        # Fault switches (set from tests; read by the serving thread).
        self.mute = False
        self.corrupt_replies = 0
        self.drop_requests = 0
        self.fragment_replies = False
        # Firmware faults: HELLO unknown (firmware older than sessions), HELLO that keeps the
        # reply cache, cached replies sent without their `cached=1` flag.
        self.no_hello = False
        self.hello_keeps_cache = False
        self.unflagged_cache = False
        self.parser_stats = ParserStats()
        self._lock = threading.Lock()
        self._times: list[int] = [now_ns()]
        self._levels: list[np.ndarray] = [np.zeros(panels)]
        self._flashes: list[list] = []          # [t_start, t_end, level]
        self._runs: list[_TriggerRun] = []
        self._executed: list[tuple[int, str]] = []
        self._boot_ns = 0
        self._cache: OrderedDict[int, tuple[str, tuple[object, ...]]] = OrderedDict()   # seq -> reply
        self._requests: queue.Queue = queue.Queue()
        self._wake_r, self._wake_w = os.pipe()
        self._stop = threading.Event()
        self._plug()
        self._thread = threading.Thread(target=self._serve, name="leds-sim", daemon=True)
        self._thread.start()

    # -- what the panels showed -------------------------------------------------------------
    def state_at(self, t_ns: int | np.ndarray) -> np.ndarray:
        """Panel levels (0..1) at host time(s) t_ns: (panels,) for a scalar, (T, panels) for an array."""
        t = np.asarray(t_ns, dtype=np.int64)
        with self._lock:
            times = np.asarray(self._times, dtype=np.int64)
            levels = np.stack(self._levels)
            flashes = [tuple(f) for f in self._flashes]
        idx = np.searchsorted(times, t, side="right") - 1
        out = np.where((idx >= 0)[..., None], levels[np.clip(idx, 0, None)], 0.0)
        for start, end, level in flashes:
            out[(t >= start) & (t < end)] = level
        return out

    def pulse_times(self) -> tuple[np.ndarray, np.ndarray]:
        """(ids, host t_ns) of every trigger pulse emitted so far."""
        now = now_ns()
        ids, times = [], []
        with self._lock:
            runs = list(self._runs)
        for run in runs:
            k = np.arange(run.n_pulses(now))
            ids.append(run.id0 + k)
            times.append(run.t0_ns + np.round(k * run.period_ns).astype(np.int64))
        if not ids:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        return np.concatenate(ids), np.concatenate(times)

    def flashes(self) -> list[tuple[int, int, float]]:
        """(host t_start_ns, t_end_ns, level) of every flash, as the controller's clock timed it
        (a flash cut short by the next one, an unplug or a reboot ends there)."""
        with self._lock:
            return [(start, end, level) for start, end, level in self._flashes]

    def executed(self) -> list[tuple[int, str]]:
        """(seq, verb) of every command executed, HELLO included (not those answered from the cache)."""
        with self._lock:
            return list(self._executed)

    # -- faults ------------------------------------------------------------------------------
    def unplug(self) -> None:
        """The USB cable is pulled: the port vanishes and the panels go dark."""
        self._request("unplug")

    def replug(self) -> None:
        """Plugged back: a new pty under the same name, a freshly booted (dark) controller."""
        self._request("replug")

    def reboot(self) -> None:
        """A watchdog reset: the link stays, the state is lost, BOOT is announced."""
        self._request("reboot")

    def inject(self, data: bytes) -> None:
        """Write raw bytes towards the host (line noise, partial frames)."""
        self._request("inject", data)

    def close(self) -> None:
        if not self._stop.is_set():
            self._stop.set()
            os.write(self._wake_w, b"x")
            self._thread.join(timeout=2.0)
            self._unplug_now()
            os.close(self._wake_r)
            os.close(self._wake_w)
            if self._tmp is not None:
                self._tmp.cleanup()

    def __enter__(self) -> SimulatedLedController:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- device internals (serving thread) ---------------------------------------------------
    def _request(self, what: str, data: bytes = b"") -> None:
        done = threading.Event()
        self._requests.put((what, data, done))
        os.write(self._wake_w, b"x")
        if not done.wait(timeout=2.0):
            raise RuntimeError(f"simulated LED controller did not handle {what}")

    def _ctrl_us(self, t_ns: int) -> int:
        return int((t_ns - self._boot_ns) * (1 + self.drift_ppm * 1e-6) // 1000)

    def _plug(self) -> None:
        self._port.plug()
        self._boot(now_ns())

    def _boot(self, t_ns: int) -> None:
        with self._lock:
            self._boot_ns = t_ns
            self._set_levels(t_ns, np.zeros(self.panels))
            self._end_outputs(t_ns)
        self._cache.clear()
        self._write(encode(0, "BOOT", self._ctrl_us(t_ns), f"fw={FIRMWARE}", f"panels={self.panels}"))

    def _end_outputs(self, t_ns: int) -> None:
        self._end_flash(t_ns)
        self._stop_triggers(t_ns)

    def _stop_triggers(self, t_ns: int) -> None:
        for run in self._runs:
            if run.t_stop_ns is None or run.t_stop_ns > t_ns:
                run.t_stop_ns = t_ns

    def _set_levels(self, t_ns: int, levels: np.ndarray) -> None:
        self._times.append(t_ns)
        self._levels.append(np.asarray(levels, dtype=float))

    def _unplug_now(self) -> None:
        if self._port.master is None:
            return
        t = now_ns()
        with self._lock:
            self._set_levels(t, np.zeros(self.panels))
            self._end_outputs(t)
        self._port.unplug()

    def _serve(self) -> None:
        parser = FrameParser(stats=self.parser_stats)
        while not self._stop.is_set():
            fds = [self._wake_r] + ([self._port.master] if self._port.master is not None else [])
            ready, _, _ = select.select(fds, [], [], 0.5)
            if self._wake_r in ready:
                os.read(self._wake_r, 64)
                self._handle_requests(parser)
            if self._port.master is not None and self._port.master in ready:
                try:
                    data = os.read(self._port.master, 4096)
                except OSError:
                    continue
                for msg in parser.feed(data):
                    self._handle(msg)

    def _handle_requests(self, parser: FrameParser) -> None:
        while True:
            try:
                what, data, done = self._requests.get_nowait()
            except queue.Empty:
                return
            if what == "unplug":
                self._unplug_now()
                parser.reset()
            elif what == "replug":
                if self._port.master is None:
                    self._plug()
            elif what == "reboot":
                parser.reset()
                self._boot(now_ns())
            elif what == "inject":
                self._write(data)
            done.set()

    def _write(self, data: bytes) -> None:
        if self._port.master is None:
            return
        if not self.fragment_replies:
            os.write(self._port.master, data)
            return
        # Torn across USB packets: three pieces with gaps, as a slow CDC stack delivers them.
        for piece in (data[:3], data[3:len(data) // 2], data[len(data) // 2:]):
            os.write(self._port.master, piece)
            time.sleep(0.003)

    def _handle(self, msg: Message) -> None:
        if self.mute:
            return
        if self.drop_requests > 0:
            self.drop_requests -= 1
            return
        if msg.verb == "HELLO" and not self.no_hello:
            # never cached: a repeated HELLO empties the cache again, which nothing can miss
            verb, args = self._hello(msg)
        elif msg.seq in self._cache:
            verb, args = self._cache[msg.seq]
            if verb == "OK" and not self.unflagged_cache:
                args = (*args, f"{CACHED}=1")
        else:
            verb, args = self._execute(msg)
            self._cache[msg.seq] = (verb, args)
            while len(self._cache) > DEDUPE_DEPTH:
                self._cache.popitem(last=False)
        reply = encode(msg.seq, verb, *args)
        if self.corrupt_replies > 0:
            self.corrupt_replies -= 1
            reply = reply[:2] + bytes([reply[2] ^ 0x01]) + reply[3:]
        self._write(reply)

    def _hello(self, msg: Message) -> tuple[str, tuple[object, ...]]:
        t = now_ns()
        if len(msg.args) != 1 or not msg.args[0].isdigit():
            return "ERR", ("BADARG", "HELLO needs a nonce")
        if not self.hello_keeps_cache:
            self._cache.clear()
        with self._lock:
            self._executed.append((msg.seq, "HELLO"))
            levels = self._levels_field()
        return "OK", (self._ctrl_us(t), f"nonce={msg.args[0]}", f"fw={FIRMWARE}", f"panels={self.panels}", levels)

    def _execute(self, msg: Message) -> tuple[str, tuple[object, ...]]:
        t = now_ns()
        try:
            args = [int(a) for a in msg.args]
        except ValueError:
            return "ERR", ("BADARG", "arguments must be integers")
        with self._lock:
            error = self._apply(msg.verb, args, t)
            if error is None:
                self._executed.append((msg.seq, msg.verb))
            extra = self._status_fields(t) if msg.verb == "STAT" and error is None else []
            if msg.verb == "TRIG" and error is None and args[0]:
                run = self._runs[-1]
                extra = [f"t0={self._ctrl_us(run.t0_ns)}", f"p0={run.id0}"]
        if error is not None:
            return "ERR", error
        return "OK", (self._ctrl_us(t), *extra)

    def _apply(self, verb: str, args: list[int], t: int) -> tuple[str, str] | None:
        current = self._levels[-1]
        if verb == "STAT":
            return None
        if verb == "LVL":
            if len(args) != self.panels or not all(0 <= a <= LEVEL_MAX for a in args):
                return ("BADARG", f"LVL needs {self.panels} levels in 0..{LEVEL_MAX}")
            self._set_levels(t, np.array([from_wire(a) for a in args]))
        elif verb == "ALL":
            if len(args) != 1 or not 0 <= args[0] <= LEVEL_MAX:
                return ("BADARG", f"ALL needs one level in 0..{LEVEL_MAX}")
            self._set_levels(t, np.full(self.panels, from_wire(args[0])))
        elif verb == "SET":
            if len(args) != 2 or not 0 <= args[0] < self.panels or not 0 <= args[1] <= LEVEL_MAX:
                return ("BADARG", f"SET needs a panel in 0..{self.panels - 1} and a level")
            new = current.copy()
            new[args[0]] = from_wire(args[1])
            self._set_levels(t, new)
        elif verb == "FLASH":
            if len(args) != 2 or not 1 <= args[0] <= 60000 or not 0 <= args[1] <= LEVEL_MAX:
                return ("BADARG", "FLASH needs a duration 1..60000 ms and a level")
            # A new flash cuts the running one short; the controller's clock times it.
            self._end_flash(t)
            length_ns = args[0] * 1_000_000 / (1 + self.drift_ppm * 1e-6)
            self._flashes.append([t, t + int(length_ns), from_wire(args[1])])
        elif verb == "TRIG":
            if len(args) != 3 or args[0] < 0 or args[1] < 0:
                return ("BADARG", "TRIG needs rate_mHz, count, width_us")
            emitted = self._pulses_emitted(t)
            self._stop_triggers(t)
            if args[0]:
                period = 1e12 / args[0] / (1 + self.drift_ppm * 1e-6)
                self._runs.append(_TriggerRun(t, period, args[1], emitted))
        else:
            return ("UNKNOWN", f"unknown command {verb}")
        return None

    def _end_flash(self, t: int) -> None:
        for flash in self._flashes:
            flash[1] = min(flash[1], t)

    def _pulses_emitted(self, t: int) -> int:
        since_boot = [r for r in self._runs if r.t0_ns >= self._boot_ns]
        return sum(r.n_pulses(t) for r in since_boot)

    def _levels_field(self) -> str:
        """The set-point as a reply field, levels=L0/L1/..."""
        return "levels=" + "/".join(str(to_wire(x)) for x in self._levels[-1])

    def _status_fields(self, t: int) -> list[str]:
        flash_left = max((f[1] - t for f in self._flashes if f[0] <= t < f[1]), default=0)
        running = [r for r in self._runs if (r.t_stop_ns is None or r.t_stop_ns > t)
                   and (not r.count or r.n_pulses(t) < r.count)]
        rate = int(round(1e12 / running[-1].period_ns / (1 + self.drift_ppm * 1e-6))) if running else 0
        return [self._levels_field(), f"flash={flash_left // 1_000_000}", f"trig={rate}", f"pulses={self._pulses_emitted(t)}"]
