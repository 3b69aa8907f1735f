"""Client of the framed ASCII controller: acknowledged commands, retries, reconnects."""

from __future__ import annotations

import threading
import time
from typing import Any

import serial

from manus_core.errors import LedRejected, LedTimeout, LedValueError, LinkLost

from .base import DEFAULT_BACKOFF, Backoff, LedController, Opener, SerialLink, check_level, now_ns
from .protocol import SEQ_MAX, FrameParser, Reply, encode, from_wire, parse_reply, to_wire


class AsciiLedController(LedController):
    """An LED/trigger controller speaking the protocol of docs/leds-protocol.md over a serial port.

    Every command waits for the acknowledgement carrying its sequence number. A command that
    gets no answer in `timeout_s` is sent again with the same sequence number (the controller
    answers a repeated number from its cache without executing it twice, so even FLASH is safe
    to repeat), up to `retries` times. A port that fails is reopened with backoff; the last
    absolute set-point is then sent again before the interrupted command.
    """

    protocol = "ascii"

    def __init__(self, port: str, panels: int = 6, baudrate: int = 115200, level: float = 1.0, *,
                 timeout_s: float = 0.25, retries: int = 3, backoff: Backoff = DEFAULT_BACKOFF,
                 opener: Opener = serial.Serial) -> None:
        super().__init__(port, panels, level)
        self.timeout_s = timeout_s
        self.retries = retries
        self._link = SerialLink(port, baudrate, backoff, self.log, opener)
        self._parser = FrameParser()
        self._seq = 0
        self._lock = threading.RLock()
        self._rebooted = False
        self._link.open()

    # -- commands ---------------------------------------------------------------------------
    def _apply(self, levels: list[float]) -> dict[str, Any]:
        return self._locked("LVL", [to_wire(x) for x in levels], levels=levels)

    def flash(self, ms: int, level: float = 1.0) -> dict[str, Any]:
        """All panels to `level` for `ms` milliseconds, then back to the set-point (controller-timed)."""
        if not 1 <= int(ms) <= 60000:
            raise LedValueError(f"flash duration {ms} ms is outside 1..60000")
        return self._locked("FLASH", [int(ms), to_wire(check_level(level))])

    def trigger(self, rate_hz: float, count: int = 0, width_us: int = 100) -> dict[str, Any]:
        """Trigger pulses at `rate_hz` (count 0: until stop_trigger); the ack gives the first
        pulse's controller time (t0, µs) and id (p0)."""
        if not 0 < rate_hz <= 10000 or count < 0 or not 1 <= width_us <= 100000:
            raise LedValueError(f"trigger rate {rate_hz} Hz, count {count}, width {width_us} µs out of range")
        return self._locked("TRIG", [int(round(rate_hz * 1000)), int(count), int(width_us)])

    def stop_trigger(self) -> dict[str, Any]:
        return self._locked("TRIG", [0, 0, 0])

    def status(self) -> dict[str, Any]:
        """The controller's state: clock (t_us), levels (0..1 per panel), flash_ms left,
        trigger rate, pulses emitted since boot."""
        record = self._locked("STAT", [])
        fields = record["reply"]
        return {"t_us": record["controller_t_us"],
                "levels": [from_wire(int(x)) for x in fields.get("levels", "").split("/") if x],
                "flash_ms": int(fields.get("flash", 0)),
                "trigger_hz": int(fields.get("trig", 0)) / 1000,
                "pulses": int(fields.get("pulses", 0))}

    def poll(self) -> None:
        """Read what the controller sent unasked; a reboot it announced restores the set-point."""
        with self._lock:
            try:
                self._handle_unsolicited(self._parser.feed(self._link.drain_input()))
            except LinkLost as exc:
                self._recover(str(exc))
            self._restore_after_reboot()

    def close(self) -> None:
        with self._lock:
            self._link.close()
        super().close()

    # -- exchange ---------------------------------------------------------------------------
    def _locked(self, verb: str, args: list[int], levels: list[float] | None = None) -> dict[str, Any]:
        with self._lock:
            record = self._command(verb, args)
            if levels is not None:
                # The set-point changes only once the controller has it: a reconnect during
                # the command re-sends the previous one, then the command itself.
                self._levels = levels
            self._restore_after_reboot()
            return record

    def _next_seq(self) -> int:
        self._seq = self._seq % SEQ_MAX + 1
        return self._seq

    def _command(self, verb: str, args: list[int], *, recover: bool = True,
                 why: str | None = None) -> dict[str, Any]:
        seq = self._next_seq()
        record = self.log.add({"seq": seq, "cmd": verb, "args": list(args), "t_send_ns": now_ns(),
                               "t_ack_ns": None, "attempts": 0, "status": "pending",
                               "controller_t_us": None, "reply": {}})
        if why:
            record["why"] = why
        frame = encode(seq, verb, *args)
        while True:
            record["attempts"] += 1
            try:
                self._link.write(frame)
                reply = self._await(seq)
            except LinkLost as exc:
                if not recover:
                    record["status"] = "disconnected"
                    raise
                # The attempt never reached a controller; it does not count against the retries.
                record["attempts"] -= 1
                self._recover(str(exc))
                continue
            if reply is not None:
                break
            if record["attempts"] > self.retries:
                record["status"] = "timeout"
                raise LedTimeout(f"LED controller on {self.port}: no answer to {verb} (seq {seq}) after "
                                 f"{record['attempts']} attempts of {self.timeout_s:g} s")
        record["t_ack_ns"] = now_ns()
        record["controller_t_us"] = reply.t_us
        if not reply.ok:
            record["status"] = "error"
            record["reply"] = {"error": reply.error}
            raise LedRejected(f"LED controller on {self.port}: {verb} (seq {seq}) refused: {reply.error}")
        record["reply"] = dict(reply.fields)
        record["status"] = "ok"
        return record

    def _await(self, seq: int) -> Reply | None:
        deadline = time.monotonic() + self.timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            messages = self._parser.feed(self._link.read(remaining))
            for i, msg in enumerate(messages):
                reply = parse_reply(msg)
                if reply is not None and reply.seq == seq:
                    self._handle_unsolicited(messages[:i] + messages[i + 1:])
                    return reply
            self._handle_unsolicited(messages)

    def _handle_unsolicited(self, messages: list) -> None:
        # Stale acknowledgements (of an attempt that already timed out) are dropped; a BOOT
        # event means the controller restarted and lost its levels.
        for msg in messages:
            if msg.seq == 0 and msg.verb == "BOOT":
                self._rebooted = True
                self.log.event("boot", port=self.port, fields=list(msg.args))

    def _restore_after_reboot(self) -> None:
        if self._rebooted:
            self._rebooted = False
            self._command("LVL", [to_wire(x) for x in self._levels], why="reboot")

    def _recover(self, reason: str) -> None:
        """Reconnect (with backoff) and put the set-point back; loops while the link keeps failing."""
        while True:
            self._link.reconnect(reason)
            self._parser.reset()
            self._rebooted = False
            try:
                self._command("LVL", [to_wire(x) for x in self._levels], recover=False, why="reconnect")
                return
            except LinkLost as exc:
                reason = str(exc)
