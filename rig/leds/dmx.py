"""DMX512 through an Enttec DMX USB Pro-compatible interface.

The widget's serial API wraps every message as 0x7E, label, length LSB, length MSB, payload,
0xE7. Label 6 ("Output Only Send DMX Packet") carries the DMX start code and 24..512 channel
slots; the widget repeats the last universe on the DMX line until it gets another, so one
message per change is enough. DMX has no acknowledgement: a command is logged as sent once
the bytes have left the host, and `status()` asks the widget for its parameters (label 3) to
prove it is alive.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import serial

from manus_core.errors import LedDisconnected, LedError, LedTimeout, LedValueError, LinkLost

from .base import DEFAULT_BACKOFF, Backoff, LedController, Opener, SerialLink, check_level, now_ns

SOM = 0x7E                     # start of message
EOM = 0xE7                     # end of message
LABEL_GET_PARAMETERS = 3
LABEL_SEND_DMX = 6
MIN_SLOTS = 24                 # DMX512 needs at least 24 slots per packet (break-to-break time)
MAX_SLOTS = 512
MAX_PAYLOAD = 600              # the widget's message size limit


def enttec_message(label: int, payload: bytes) -> bytes:
    """One widget message: SOM, label, 16-bit little-endian length, payload, EOM."""
    if not 0 <= label <= 255 or len(payload) > MAX_PAYLOAD:
        raise ValueError(f"label {label} / payload of {len(payload)} bytes out of range")
    return bytes([SOM, label, len(payload) & 0xFF, len(payload) >> 8]) + bytes(payload) + bytes([EOM])


def send_dmx_message(slots: bytes, start_code: int = 0) -> bytes:
    """Label 6 with the start code (0 for dimmer data) and the slots, padded to 24."""
    if len(slots) > MAX_SLOTS:
        raise ValueError(f"a DMX universe has at most {MAX_SLOTS} slots, got {len(slots)}")
    data = bytes(slots) + bytes(max(0, MIN_SLOTS - len(slots)))
    return enttec_message(LABEL_SEND_DMX, bytes([start_code]) + data)


def get_parameters_message() -> bytes:
    """Label 3 request; the two payload bytes ask for 0 bytes of user configuration."""
    return enttec_message(LABEL_GET_PARAMETERS, b"\x00\x00")


def parse_parameters(payload: bytes) -> dict[str, float]:
    """A label-3 reply: firmware version, break and mark-after-break (units of 10.67 µs), rate."""
    if len(payload) < 5:
        raise ValueError(f"widget parameters reply of {len(payload)} bytes, expected at least 5")
    return {"firmware": payload[0] | payload[1] << 8,
            "break_us": round(payload[2] * 10.67, 2),
            "mab_us": round(payload[3] * 10.67, 2),
            "rate_hz": payload[4]}


class EnttecParser:
    """Incremental decoder of widget messages; bytes that do not form one are skipped."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.skipped = 0

    def feed(self, data: bytes) -> list[tuple[int, bytes]]:
        self._buf += data
        out = []
        buf = self._buf
        while True:
            start = buf.find(SOM)
            if start < 0:
                self.skipped += len(buf)
                buf.clear()
                return out
            self.skipped += start
            del buf[:start]
            if len(buf) < 4:
                return out
            length = buf[2] | buf[3] << 8
            if length > MAX_PAYLOAD:
                self.skipped += 1
                del buf[:1]
                continue
            if len(buf) < length + 5:
                return out
            if buf[length + 4] != EOM:
                self.skipped += 1
                del buf[:1]
                continue
            out.append((buf[1], bytes(buf[4:4 + length])))
            del buf[:length + 5]


class DmxLedController(LedController):
    """LED panels on DMX channels start_channel, start_channel+1, ... (one 8-bit channel each).

    Flashes are timed by the host (a timer restores the set-point), so they are as exact as
    the host's scheduling, not as the controller-timed flashes of the ASCII protocol. DMX has
    no trigger output.
    """

    protocol = "dmx"

    def __init__(self, port: str, panels: int = 6, baudrate: int = 57600, level: float = 1.0, *,
                 start_channel: int = 1, slots: int | None = None, timeout_s: float = 0.25,
                 retries: int = 3, backoff: Backoff = DEFAULT_BACKOFF,
                 opener: Opener = serial.Serial) -> None:
        super().__init__(port, panels, level)
        self.slots = max(MIN_SLOTS, panels + start_channel - 1) if slots is None else slots
        if not start_channel >= 1 or start_channel + panels - 1 > min(self.slots, MAX_SLOTS):
            raise LedValueError(f"DMX channels {start_channel}..{start_channel + panels - 1} do not fit "
                                f"in a universe of {self.slots} slots")
        self.start_channel = start_channel
        self.timeout_s = timeout_s
        self.retries = retries
        self._link = SerialLink(port, baudrate, backoff, self.log, opener)
        self._parser = EnttecParser()
        self._lock = threading.RLock()
        self._flash_until_ns = 0
        self._flash_timer: threading.Timer | None = None
        self._count = 0
        self._closed = False
        self._link.open()

    def universe(self, levels: list[float]) -> bytes:
        slots = bytearray(self.slots)
        for i, level in enumerate(levels):
            slots[self.start_channel - 1 + i] = int(round(level * 255))
        return bytes(slots)

    def _apply(self, levels: list[float]) -> dict[str, Any]:
        with self._lock:
            if now_ns() < self._flash_until_ns:
                # The running flash restores the new set-point when it ends.
                self._levels = levels
                return self.log.add({"seq": self._next(), "cmd": "DMX", "levels": levels,
                                     "t_send_ns": now_ns(), "status": "deferred (flash)"})
            record = self._send(levels, "DMX")
            self._levels = levels
            return record

    def flash(self, ms: int, level: float = 1.0) -> dict[str, Any]:
        if not 1 <= int(ms) <= 60000:
            raise LedValueError(f"flash duration {ms} ms is outside 1..60000")
        with self._lock:
            record = self._send([check_level(level)] * self.panels, "FLASH", ms=int(ms))
            self._flash_until_ns = record["t_done_ns"] + int(ms) * 1_000_000
            if self._flash_timer is not None:
                self._flash_timer.cancel()
            self._flash_timer = threading.Timer(int(ms) / 1000, self._end_flash)
            self._flash_timer.daemon = True
            self._flash_timer.start()
            return record

    def _end_flash(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._flash_until_ns = 0
            self._flash_timer = None
            try:
                self._send(self._levels, "FLASH-END")
            except LedError:
                # Logged by _send; the next command will try again.
                pass

    def trigger(self, rate_hz: float, count: int = 0, width_us: int = 100) -> dict[str, Any]:
        raise LedError(f"LED controller on {self.port}: a DMX interface has no trigger output "
                       "(use the ascii protocol for hardware-trigger sync)")

    def stop_trigger(self) -> dict[str, Any]:
        return self.trigger(0)

    def status(self) -> dict[str, Any]:
        """The widget's parameters (label 3); raises LedTimeout when it does not answer."""
        with self._lock:
            for _ in range(self.retries + 1):
                try:
                    self._parser.feed(self._link.drain_input())
                    self._link.write(get_parameters_message())
                    payload = self._await(LABEL_GET_PARAMETERS)
                except LinkLost as exc:
                    self._recover(str(exc))
                    continue
                if payload is not None:
                    return {**parse_parameters(payload), "levels": list(self._levels)}
            raise LedTimeout(f"LED controller on {self.port}: DMX widget did not answer the parameters "
                             f"request after {self.retries + 1} attempts of {self.timeout_s:g} s")

    def close(self) -> None:
        with self._lock:
            self._closed = True
            if self._flash_timer is not None:
                self._flash_timer.cancel()
            self._link.close()
        super().close()

    def _next(self) -> int:
        self._count += 1
        return self._count

    def _send(self, levels: list[float], cmd: str, **extra: Any) -> dict[str, Any]:
        record = self.log.add({"seq": self._next(), "cmd": cmd, "levels": list(levels), **extra,
                               "t_send_ns": now_ns(), "t_done_ns": None, "status": "pending"})
        message = send_dmx_message(self.universe(levels))
        while True:
            try:
                self._link.write(message)
                break
            except LinkLost as exc:
                record["status"] = "disconnected"
                try:
                    self._recover(str(exc))
                except LedDisconnected as lost:
                    record["error"] = f"{lost}; {cmd} not sent"
                    raise LedDisconnected(record["error"]) from None
        record["t_done_ns"] = now_ns()
        record["status"] = "sent"
        return record

    def _recover(self, reason: str) -> None:
        # The universe is absolute: the reconnect resends the set-point and nothing else.
        while True:
            self._link.reconnect(reason)
            try:
                self._link.write(send_dmx_message(self.universe(self._levels)))
                self.log.add({"seq": self._next(), "cmd": "DMX", "levels": list(self._levels),
                              "why": "reconnect", "t_send_ns": now_ns(), "status": "sent"})
                return
            except LinkLost as exc:
                reason = str(exc)

    def _await(self, label: int) -> bytes | None:
        deadline = time.monotonic() + self.timeout_s
        while (remaining := deadline - time.monotonic()) > 0:
            for got, payload in self._parser.feed(self._link.read(remaining)):
                if got == label:
                    return payload
        return None
