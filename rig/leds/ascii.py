"""Client of the framed ASCII controller: acknowledged commands, retries, reconnects."""

from __future__ import annotations

import secrets
import threading
import time
from typing import Any

import serial

from manus_core.errors import LedDisconnected, LedError, LedRejected, LedStaleReply, LedTimeout, LedValueError, LinkLost

from .base import DEFAULT_BACKOFF, Backoff, LedController, Opener, SerialLink, check_level, now_ns
from .protocol import CACHED, NONCE_MAX, SEQ_MAX, FrameParser, Reply, encode, from_wire, parse_reply, to_wire

# The log's status of a command that failed, by what it raised (anything else: "error").
FAILURES = ((LedTimeout, "timeout"), ((LedDisconnected, LinkLost), "disconnected"), (LedStaleReply, "stale"))


class AsciiLedController(LedController):
    """An LED/trigger controller speaking the protocol of docs/leds-protocol.md over a serial port.

    Opening the port starts a session: HELLO with a random nonce empties the controller's reply
    cache, so that the sequence numbers of this connection (from 1, like every other's) are
    answered by this connection's commands only; `session` keeps the handshake. Every command
    waits for the acknowledgement carrying its sequence number. A command that gets no answer in
    `timeout_s` is sent again with the same sequence number (the controller answers a repeated
    number from its cache without executing it twice, so even FLASH is safe to repeat), up to
    `retries` times. A reply that cannot be the command's own (flagged as cached for a command
    sent once, or older on the controller's clock than the previous reply) raises LedStaleReply.
    A port that fails is reopened with backoff; the last absolute set-point is then sent again
    before the interrupted command. A command that fails is logged with its status and error.
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
        self._t_floor_us: int | None = None   # controller time of the latest reply since (re)connecting
        self.session: dict[str, Any] = {}
        self._link.open()
        try:
            self._open_session()
        except BaseException:
            self._link.close()
            raise

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
                "levels": self._wire_levels("STAT", fields),
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
    def _open_session(self) -> None:
        nonce = secrets.randbelow(NONCE_MAX) + 1
        seq = self._next_seq()
        # Not in the command log: the log is what the panels were asked to do.
        record = self._record(seq, "HELLO", [nonce])
        try:
            reply = self._exchange(record, encode(seq, "HELLO", nonce), recover=False, nonce=nonce)
        except LedRejected:
            raise LedError(f"LED controller on {self.port}: refused HELLO, so its firmware predates sessions "
                           "(docs/leds-protocol.md) and could answer this process's commands with replies kept "
                           "for an earlier one; update the firmware") from None
        except LinkLost as exc:
            raise LedError(f"LED controller on {self.port}: failed while opening ({exc})") from None
        self.session = {"nonce": nonce, "t_send_ns": record["t_send_ns"], "t_ack_ns": now_ns(),
                        "controller_t_us": reply.t_us, **{k: v for k, v in reply.fields.items() if k != "nonce"}}
        levels = self._wire_levels("HELLO", reply.fields)
        if len(levels) == self.panels:
            # start from the panels as an earlier process left them: one panel's SET keeps the others
            self._levels = levels

    def _wire_levels(self, verb: str, fields: dict[str, str]) -> list[float]:
        """A reply's `levels=L0/L1/...` field as levels 0..1 ([] when it has none)."""
        text = fields.get("levels", "")
        try:
            return [from_wire(int(x)) for x in text.split("/") if x]
        except ValueError:
            raise LedError(f"LED controller on {self.port}: {verb} reply has unreadable levels {text!r}") from None

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

    @staticmethod
    def _record(seq: int, verb: str, args: list[int]) -> dict[str, Any]:
        return {"seq": seq, "cmd": verb, "args": list(args), "t_send_ns": now_ns(), "t_ack_ns": None,
                "attempts": 0, "status": "pending", "controller_t_us": None, "reply": {}}

    def _command(self, verb: str, args: list[int], *, recover: bool = True,
                 why: str | None = None) -> dict[str, Any]:
        seq = self._next_seq()
        record = self.log.add(self._record(seq, verb, args))
        if why:
            record["why"] = why
        try:
            reply = self._exchange(record, encode(seq, verb, *args), recover=recover)
        except LedDisconnected as exc:
            lost = LedDisconnected(f"{exc}; {verb} (seq {seq}) not acknowledged")
            self._failed(record, lost)
            raise lost from None
        except (LedError, LinkLost) as exc:
            self._failed(record, exc)
            raise
        record["reply"] = dict(reply.fields)
        record["status"] = "ok"
        return record

    @staticmethod
    def _failed(record: dict[str, Any], exc: Exception) -> None:
        record["status"] = next((status for kinds, status in FAILURES if isinstance(exc, kinds)), "error")
        record["error"] = str(exc)

    def _exchange(self, record: dict[str, Any], frame: bytes, *, recover: bool,
                  nonce: int | None = None) -> Reply:
        """Send `frame` until its reply comes (retries, reconnects); raise on ERR or a stale reply."""
        verb, seq = record["cmd"], record["seq"]
        writes = 0
        while True:
            record["attempts"] += 1
            try:
                writes += 1
                self._link.write(frame)
                reply = self._await(seq, nonce)
            except LinkLost as exc:
                if not recover:
                    raise
                # The attempt never reached a controller; it does not count against the retries.
                record["attempts"] -= 1
                self._recover(str(exc))
                continue
            if reply is not None:
                break
            if record["attempts"] > self.retries:
                raise LedTimeout(f"LED controller on {self.port}: no answer to {verb} (seq {seq}) after "
                                 f"{record['attempts']} attempts of {self.timeout_s:g} s")
        record["t_ack_ns"] = now_ns()
        record["controller_t_us"] = reply.t_us
        if not reply.ok:
            record["reply"] = {"error": reply.error}
            raise LedRejected(f"LED controller on {self.port}: {verb} (seq {seq}) refused: {reply.error}")
        self._check_own(verb, seq, reply, resent=writes > 1)
        return reply

    def _check_own(self, verb: str, seq: int, reply: Reply, *, resent: bool) -> None:
        """Refuse a reply the controller kept for an earlier request with the same number.

        A reply from the cache is right only for a frame this connection sent before; and a
        reply taking effect before the previous reply did cannot answer a later request.
        """
        if reply.fields.get(CACHED) == "1" and not resent:
            why = "a reply the controller kept for an earlier request with the same number"
        elif self._t_floor_us is not None and reply.t_us < self._t_floor_us:
            why = (f"a reply from controller time {reply.t_us} µs, before its previous reply "
                   f"({self._t_floor_us} µs)")
        else:
            self._t_floor_us = reply.t_us
            return
        raise LedStaleReply(f"LED controller on {self.port}: {verb} (seq {seq}) was answered with {why}, so it "
                            "was not carried out; the controller's firmware must empty its reply cache on HELLO "
                            "(docs/leds-protocol.md)")

    def _await(self, seq: int, nonce: int | None = None) -> Reply | None:
        """The reply to `seq` (for HELLO: the one that carries `nonce`, or an ERR), None on timeout."""
        deadline = time.monotonic() + self.timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            messages = self._parser.feed(self._link.read(remaining))
            for i, msg in enumerate(messages):
                reply = parse_reply(msg)
                if (reply is not None and reply.seq == seq
                        and (nonce is None or not reply.ok or reply.fields.get("nonce") == str(nonce))):
                    self._handle_unsolicited(messages[:i] + messages[i + 1:])
                    return reply
            self._handle_unsolicited(messages)

    def _handle_unsolicited(self, messages: list) -> None:
        # Stale acknowledgements (of an attempt that already timed out, or of an earlier
        # connection before HELLO) are dropped; a BOOT event means the controller restarted,
        # lost its levels and restarted its clock.
        for msg in messages:
            if msg.seq == 0 and msg.verb == "BOOT":
                self._rebooted = True
                self._t_floor_us = None
                self.log.event("boot", port=self.port, fields=list(msg.args))

    def _restore_after_reboot(self) -> None:
        if self._rebooted:
            self._rebooted = False
            self._command("LVL", [to_wire(x) for x in self._levels], why="reboot")

    def _recover(self, reason: str) -> None:
        """Reconnect (with backoff) and put the set-point back; loops while the link keeps failing.

        The session goes on (no HELLO): a controller that stayed powered still holds this
        connection's replies, and the interrupted command is sent again with its number.
        """
        while True:
            self._link.reconnect(reason)
            self._parser.reset()
            self._rebooted = False
            # a replugged controller has rebooted: its clock starts again
            self._t_floor_us = None
            try:
                self._command("LVL", [to_wire(x) for x in self._levels], recover=False, why="reconnect")
                return
            except LinkLost as exc:
                reason = str(exc)
