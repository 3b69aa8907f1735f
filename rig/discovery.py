"""What is plugged in: cameras (V4L2 by-id, Aravis GigE/USB3 Vision) and serial ports.

`manus-capture rig list` prints this; the `device` of each camera is what rig.toml's
`device` key takes.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

ENTTEC_USB_IDS = {(0x0403, 0x6001)}     # FTDI FT232R, which the DMX USB Pro and its clones use


@dataclass(frozen=True)
class FoundCamera:
    backend: str          # v4l2 | aravis
    device: str           # what rig.toml's `device` takes: a /dev/v4l/by-id path, an Aravis id
    model: str = ""
    vendor: str = ""
    serial: str = ""
    address: str = ""     # /dev/videoN, IP address, USB bus id
    protocol: str = ""    # UVC, GigEVision, USB3Vision, Fake


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
    from serial.tools import list_ports

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


def discover(*, v4l2: bool = True, aravis: bool = True, serial: bool = True,
             aravis_fake: bool = False) -> Discovery:
    """Ask every backend; one that cannot be asked leaves a note instead of failing the rest."""
    result = Discovery()
    if v4l2:
        from rig.cameras.v4l2 import list_v4l2_cameras

        result.cameras += list_v4l2_cameras()
    if aravis:
        from rig.cameras import CameraError
        from rig.cameras.aravis import list_aravis_cameras

        try:
            result.cameras += list_aravis_cameras(include_fake=aravis_fake)
        except CameraError as exc:
            result.notes.append(f"aravis: {exc}")
    if serial:
        result.ports = list_serial_ports()
    return result
