"""One Camera protocol, one module per backend (sim, v4l2, aravis).

A backend hands out frames as they came from the device: MJPEG bytes where the camera encodes
(UVC, the simulated cube), raw pixels otherwise, each with the device's sequence number and
timestamp and the host's receive time. The recorder never decodes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable
from manus_core.errors import CameraDisconnected, CameraError


@dataclass(frozen=True)
class Frame:
    data: bytes          # JPEG bytes when encoding == "jpeg", else packed pixels
    seq: int             # device sequence number; gaps are drops
    t_device_ns: int     # device clock at mid-exposure (or the device's own timestamp point)
    t_host_ns: int       # host clock when the frame arrived
    width: int
    height: int
    encoding: str = "jpeg"  # jpeg | mono8 | bgr8 | bayer_rg8 | ...


@dataclass(frozen=True)
class CameraInfo:
    id: str
    backend: str
    model: str
    serial: str
    width: int
    height: int
    fps: float
    pixel_format: str
    can_trigger: bool = False


@runtime_checkable
class Camera(Protocol):
    """open -> configure -> start -> read* -> stop -> close. read() returns None on timeout."""

    def open(self) -> None: ...

    def configure(self) -> None: ...

    def start(self) -> None: ...

    def read(self, timeout_s: float = 1.0) -> Frame | None: ...

    def trigger(self) -> None: ...

    def stop(self) -> None: ...

    def close(self) -> None: ...

    def info(self) -> CameraInfo: ...
