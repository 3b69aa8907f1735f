"""What is plugged in: the cameras every registered backend finds, and serial ports.

`manus-capture rig list` prints this; the `device` of each camera is what rig.toml's
`device` key takes.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import asdict, dataclass, field

from serial.tools import list_ports

from manus_core.errors import CameraError

from .backends import BACKENDS
from .cameras import FoundCamera

ENTTEC_USB_IDS = {(0x0403, 0x6001)}     # FTDI FT232R, which the DMX USB Pro and its clones use


@dataclass(frozen=True)
class FoundPort:
    device: str
    description: str = ""
    hwid: str = ""
    serial: str = ""
    guess: str = ""       # e.g. "Enttec DMX USB Pro-compatible (FTDI)"


@dataclass
class Discovery:
    cameras: list[FoundCamera] = field(default_factory=list)
    ports: list[FoundPort] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)   # backends that could not be asked, and why

    def to_dict(self) -> dict:
        return {"cameras": [asdict(c) for c in self.cameras], "ports": [asdict(p) for p in self.ports],
                "notes": list(self.notes)}


def list_serial_ports() -> list[FoundPort]:
    """Serial ports from pyserial, with a guess at what an FTDI or CDC-ACM device might be."""
    found = []
    for port in sorted(list_ports.comports(), key=lambda p: p.device):
        guess = ""
        if (port.vid, port.pid) in ENTTEC_USB_IDS:
            guess = "FTDI serial (Enttec DMX USB Pro-compatible interfaces use it)"
        elif port.device.startswith("/dev/ttyACM"):
            guess = "USB CDC-ACM (microcontroller LED controller?)"
        found.append(FoundPort(port.device, port.description or "", port.hwid or "",
                               port.serial_number or "", guess))
    return found


def discover(*, skip: Collection[str] = (), fake: bool = False, serial: bool = True) -> Discovery:
    """Ask every backend that can discover (but those in `skip`); `fake` also lists the fake
    devices a backend has (Aravis's Fake_1). A backend that cannot be asked leaves a note
    instead of failing the rest."""
    result = Discovery()
    for name, backend in BACKENDS.items():
        if backend.discover is None or name in skip:
            continue
        try:
            result.cameras += backend.discover(fake)
        except CameraError as exc:
            result.notes.append(f"{name}: {exc}")
    if serial:
        result.ports = list_serial_ports()
    return result
