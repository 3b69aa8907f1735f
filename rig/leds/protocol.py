"""The framed ASCII protocol of the LED/trigger controller (docs/leds-protocol.md is the spec).

One frame per line: ``$SEQ,VERB[,ARG...]*CRC\\n`` where CRC is CRC-16/CCITT-FALSE of the bytes
between ``$`` and ``*`` as four upper-case hex digits. Both ends use the same parser, which
resynchronizes on the next ``$`` after garbage, a torn frame or a bad checksum, so line noise
costs at most the frame it hit.
"""

from __future__ import annotations

from dataclasses import dataclass, field

MAX_FRAME = 255          # bytes from '$' to '\n'; longer input is noise
LEVEL_MAX = 1000         # wire levels are integers 0..1000 (tenths of a percent)
SEQ_MAX = 65535          # host sequence numbers run 1..65535 and wrap to 1; 0 is the controller's
NONCE_MAX = 999_999_999  # HELLO nonces are 1..NONCE_MAX, drawn at random for each connection
CACHED = "cached"        # reply field: "cached=1" marks a reply answered from the controller's cache

VERBS = ("HELLO", "SET", "ALL", "LVL", "FLASH", "TRIG", "STAT")


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor).

    Chosen because every microcontroller SDK ships it; the check value of b"123456789" is 0x29B1.
    """
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
            crc &= 0xFFFF
    return crc


@dataclass(frozen=True)
class Message:
    """One decoded frame: sequence number, verb and its arguments (all as text)."""

    seq: int
    verb: str
    args: tuple[str, ...] = ()


def encode(seq: int, verb: str, *args: object) -> bytes:
    """The wire bytes of one frame, checksum and newline included."""
    body = ",".join([str(seq), verb, *(str(a) for a in args)]).encode("ascii")
    frame = b"$" + body + b"*" + f"{crc16(body):04X}".encode("ascii") + b"\n"
    if len(frame) > MAX_FRAME:
        raise ValueError(f"frame of {len(frame)} bytes exceeds {MAX_FRAME}")
    return frame


@dataclass
class ParserStats:
    garbage_bytes: int = 0     # bytes outside any frame
    bad_frames: int = 0        # frames with a wrong checksum or an unreadable body
    torn_frames: int = 0       # frames cut short by the next '$' or by overflow


@dataclass
class FrameParser:
    """Incremental decoder: feed() any chunk of bytes, get back the complete valid frames."""

    stats: ParserStats = field(default_factory=ParserStats)
    _buf: bytearray = field(default_factory=bytearray)

    def feed(self, data: bytes) -> list[Message]:
        self._buf += data
        out: list[Message] = []
        buf = self._buf
        while True:
            start = buf.find(b"$")
            if start < 0:
                self.stats.garbage_bytes += len(buf)
                buf.clear()
                break
            if start:
                self.stats.garbage_bytes += start
                del buf[:start]
            end = buf.find(b"\n")
            restart = buf.find(b"$", 1)
            if restart >= 0 and (end < 0 or restart < end):
                # A new frame began before this one ended: this one was torn on the line.
                self.stats.torn_frames += 1
                del buf[:restart]
                continue
            if end < 0:
                if len(buf) > MAX_FRAME:
                    self.stats.torn_frames += 1
                    buf.clear()
                break
            line = bytes(buf[1:end]).rstrip(b"\r")
            del buf[:end + 1]
            msg = _decode(line)
            if msg is None:
                self.stats.bad_frames += 1
            else:
                out.append(msg)
        return out

    def reset(self) -> None:
        self._buf.clear()


def _decode(line: bytes) -> Message | None:
    body, star, crc_text = line.rpartition(b"*")
    if not star or len(crc_text) != 4:
        return None
    try:
        if int(crc_text, 16) != crc16(body):
            return None
        fields = body.decode("ascii").split(",")
        seq = int(fields[0])
    except (ValueError, UnicodeDecodeError):
        return None
    if len(fields) < 2 or not 0 <= seq <= SEQ_MAX or not fields[1]:
        return None
    return Message(seq, fields[1], tuple(fields[2:]))


@dataclass(frozen=True)
class Reply:
    """A controller's answer: OK with its clock and key=value fields, or ERR with a code."""

    seq: int
    ok: bool
    t_us: int | None = None
    fields: dict[str, str] = field(default_factory=dict)
    error: str = ""


def parse_reply(msg: Message) -> Reply | None:
    """A Reply from an OK/ERR frame; None for anything else (events, echoes)."""
    if msg.verb == "OK":
        try:
            t_us = int(msg.args[0])
        except (IndexError, ValueError):
            return None
        fields = dict(a.split("=", 1) for a in msg.args[1:] if "=" in a)
        return Reply(msg.seq, True, t_us, fields)
    if msg.verb == "ERR":
        return Reply(msg.seq, False, error=":".join(msg.args) or "unspecified")
    return None


def to_wire(level: float) -> int:
    return int(round(level * LEVEL_MAX))


def from_wire(value: int) -> float:
    return value / LEVEL_MAX
