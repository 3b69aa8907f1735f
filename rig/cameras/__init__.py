"""One Camera protocol, and what a backend (sim, v4l2, aravis, a test's fake) provides behind it.

A backend hands out frames as they came from the device: MJPEG bytes where the camera encodes
(UVC, the simulated cube), raw pixels otherwise, each with the device's sequence number and
timestamp and the host's receive time. The recorder never decodes.

A backend is a `Backend` record: how it opens its cameras for a take, how it finds the devices
plugged in (`rig list`), and, for the simulator, the clock a take runs on. rig.backends lists
them by name; the recorder and discovery ask that registry and never branch on a backend.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from manus_core.errors import CameraDisconnected, CameraError
from manus_core.rig_config import CameraConfig, RigConfig

from ..clock import Clock

__all__ = ["Backend", "Camera", "CameraDisconnected", "CameraError", "CameraInfo", "FoundCamera", "Frame",
           "TakeCameras", "TakeSetup"]


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


@dataclass(frozen=True)
class FoundCamera:
    """A camera plugged into this machine, as `rig list` shows it."""

    backend: str          # v4l2 | aravis
    device: str           # what rig.toml's `device` takes: a /dev/v4l/by-id path, an Aravis id
    model: str = ""
    vendor: str = ""
    serial: str = ""
    address: str = ""     # /dev/videoN, IP address, USB bus id
    protocol: str = ""    # UVC, GigEVision, USB3Vision, Fake


@dataclass(frozen=True)
class TakeSetup:
    """What a backend is told when it opens its cameras for one take."""

    rig: RigConfig
    cameras: tuple[CameraConfig, ...]   # the cameras to open (a backend gets its own), in rig.toml order
    kind: str
    duration_s: float
    clock: Clock                        # the take's clock
    take_dir: Path
    # the LED panels' mean level (0..1) at a take-clock time, where the controller is simulated
    lighting: Callable[[int], float] | None = None
    label_frames: Sequence[int] | None = None   # frames the simulator renders labels of


@dataclass(frozen=True)
class TakeCameras:
    """A backend's cameras for one take (not opened yet: the recorder opens them)."""

    cameras: Mapping[str, Camera]
    t0_ns: int | None = None            # tick 0 on the take's clock; None: the recorder sets it
    note: str = ""                      # take.json's backend_note
    # runs after the cameras are closed; returns extra take.json fields (the simulator's ground truth)
    finish: Callable[[], dict[str, Any]] | None = None


@dataclass(frozen=True)
class Backend:
    """One camera backend, registered by name in rig.backends."""

    name: str
    open: Callable[[TakeSetup], TakeCameras]
    # the cameras plugged in (argument: also list fake devices); None: nothing to discover
    discover: Callable[[bool], list[FoundCamera]] | None = None
    # a backend that runs takes on a clock of its own (the simulator renders on a virtual one);
    # None: the host's CLOCK_MONOTONIC, which every real camera's host times are on
    clock: Callable[[RigConfig], Clock] | None = None
