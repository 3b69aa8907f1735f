"""rig.toml: the rig's configuration, as frozen dataclasses validated on load.

The field annotations carry the rules (types, ranges, closed tables; see manus_core.validation),
and every error names the file, the key and what is wrong, in one line. rig_to_toml writes a rig
back (tomli-w); load_rig of that text gives an equal rig.
"""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal, get_args

import numpy as np
import tomli_w
from pydantic import AfterValidator, Field
from pydantic_core import PydanticCustomError

from manus_core.errors import ConfigError
from manus_core.validation import CLOSED, NOT_A_KEY, Bool, Float, Int, Str, between, validate, worded

BackendName = Literal["sim", "v4l2", "aravis"]
SyncMode = Literal["free-run", "software-trigger", "hardware-trigger"]
BACKENDS = get_args(BackendName)
SYNC_MODES = get_args(SyncMode)
MIN_SIDE, MAX_SIDE = 16, 16384       # pixels: no camera gives a smaller or a larger image
MAX_FPS = 10000                       # a camera checks its own range when it is opened
PLACEHOLDER = "CHANGE-ME"             # the device `rig init` writes for a real camera, to be replaced
# the simulated hands (their bones are rig.sim.hand.SUBJECTS; the base layer cannot import them)
SIM_SUBJECTS = ("s01", "s02", "s03")



def _sim_subject(value: str) -> str:
    if value not in SIM_SUBJECTS and not value.endswith(".toml"):
        raise PydanticCustomError("subject", f"unknown subject {value!r} (known: {', '.join(SIM_SUBJECTS)}, "
                                             "or a subject file NAME.toml)")
    return value


Vector3 = tuple[Float, Float, Float]
Level = between(Float, 0, 1)
Side = between(Int, MIN_SIDE, MAX_SIDE, "pixels")
Offset = between(Float, -0.1, 0.1, "of the image's side")
Rate = between(Float, 0, MAX_FPS, "frames per second", low_open=True)
Milliseconds = between(Float, 0, 1000, "ms")
Microseconds = between(Float, 0, 1e6, "us")
SimSubject = Annotated[Str, AfterValidator(_sim_subject)]
Backend = Annotated[BackendName, worded(f"unknown backend {{value}} (known: {', '.join(BACKENDS)})")]


@dataclass(frozen=True)
class SimCameraConfig:
    """Per-camera parameters of the simulated backend; `rig init` writes realized values."""

    __pydantic_config__ = CLOSED   # unknown keys are errors

    position: Vector3                 # camera centre, world frame, metres
    look_at: Vector3 = (0.0, 0.0, 0.0)
    up: Vector3 = (0.0, 0.0, 1.0)
    hfov_deg: between(Float, 0, 180, "degrees", low_open=True, high_open=True) = 70.0
    # the principal point's offset from the image centre, as fractions of width and height: real
    # sensors sit a little off their lens's axis, and a calibration must find where
    principal_offset: tuple[Offset, Offset] = (0.0, 0.0)
    aspect: between(Float, 0.9, 1.1) = 1.0   # fy / fx: pixels are square only to a tolerance
    dist: tuple[Float, Float, Float, Float, Float] = (0.0, 0.0, 0.0, 0.0, 0.0)   # k1, k2, p1, p2, k3
    # device clock minus host clock at the take's start
    clock_offset_ms: between(Float, -1e6, 1e6, "ms") = 0.0
    # device clock rate error; the sync report takes more than 1000 ppm for timestamps in another unit
    drift_ppm: between(Float, -1000, 1000, "ppm") = 0.0
    phase_ms: Milliseconds = 0.0      # free-run: first mid-exposure after the nominal tick
    timestamp_jitter_us: Microseconds = 0.0  # noise on the device timestamp
    trigger_latency_us: Microseconds = 0.0   # triggered: mean delay trigger -> mid-exposure
    trigger_jitter_us: Microseconds = 0.0
    latency_ms: Milliseconds = 2.0    # mid-exposure -> host arrival (readout + transfer), mean
    latency_jitter_ms: Milliseconds = 0.2
    # probability that a frame never reaches the host
    drop_rate: between(Float, 0, 1, high_open=True) = 0.0


@dataclass(frozen=True)
class CameraConfig:
    __pydantic_config__ = CLOSED   # unknown keys are errors

    id: Annotated[Str, Field(min_length=1)]
    backend: Backend
    device: Annotated[Str, Field(min_length=1)]   # serial number, /dev/v4l/by-id path, or sim:N
    width: Side = 1280
    height: Side = 720
    fps: Rate = 120.0
    pixel_format: Str = "MJPG"
    exposure_us: between(Float, 0, 1e6, "us", low_open=True) = 2000.0
    gain_db: Float = 0.0
    sim: SimCameraConfig | None = None


@dataclass(frozen=True)
class LedConfig:
    __pydantic_config__ = CLOSED   # unknown keys are errors

    port: Str                         # serial port, or "sim" for the simulated controller
    protocol: Literal["ascii", "dmx", "sim"] = "ascii"
    panels: between(Int, 1, 512) = 6  # a DMX universe has 512 channels
    baudrate: Annotated[Int, Field(gt=0)] = 115200
    level: Level = 1.0                # default level


@dataclass(frozen=True)
class StorageConfig:
    __pydantic_config__ = CLOSED   # unknown keys are errors

    root: Str = "sessions"
    min_free_gb: Annotated[Float, Field(ge=0)] = 1.0
    # for backends that hand out raw frames
    jpeg_quality: between(Int, 1, 100) = 90
    # "444" keeps colour at full resolution: the paint key and the hand/object colour models decide
    # the pixels along small painted spots on colour (paint and skin are close in brightness), and
    # 4:2:0 halves colour resolution for about 25 % smaller frames
    jpeg_chroma: Literal["444", "420"] = "444"

    def jpeg_params(self) -> list[int]:
        """cv2.imencode parameters of the stored JPEG frames."""
        import cv2  # the base layer loads OpenCV (~0.2 s) only where frames are encoded

        sampling = {"444": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444, "420": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420}
        return [cv2.IMWRITE_JPEG_QUALITY, int(self.jpeg_quality),
                cv2.IMWRITE_JPEG_SAMPLING_FACTOR, sampling[self.jpeg_chroma]]


@dataclass(frozen=True)
class SimConfig:
    """The simulated world; the per-camera clock and optics live in each camera's `sim` table."""

    __pydantic_config__ = CLOSED   # unknown keys are errors

    cube_edge: between(Float, 0.5, 3, "m") = 1.2   # the table (0.4 m) stands inside
    # 5 x 5 tags of 16 cm a wall and on the table's sides: intrinsics from the tags down to 320x180
    # (docs/calibration.md); smaller tags make the walls' textures huge
    tag_size: between(Float, 0.02, 1, "m") = 0.16
    tags_per_wall: between(Int, 0, 9) = 5   # 6 walls of 9x9 tags use 486 of the 587 ids of 36h11
    table_tags: Bool = True   # tags on the table's sides too (up to 36 more ids)
    # a built-in subject, or a subject file (docs/simulation.md) ending in .toml
    subject: SimSubject = "s01"
    object: Literal["box", "mug", "sphere"] = "mug"
    paint: Bool = False
    # 0: as fast as rendering allows (virtual clock); 1: real time
    time_scale: between(Float, 0, 10) = 0.0
    noise_sigma: between(Float, 0, 255, "grey levels") = 2.0   # image noise
    supersample: between(Int, 1, 8) = 2  # anti-aliasing of the hand, object and table edges
    seed: Int = 0


@dataclass(frozen=True)
class RigConfig:
    __pydantic_config__ = CLOSED   # unknown keys are errors

    name: Str
    cameras: tuple[CameraConfig, ...]
    layout: Str = "custom"
    fps: Rate = 120.0
    sync: SyncMode = "free-run"
    leds: LedConfig | None = None
    storage: StorageConfig = field(default_factory=StorageConfig)
    sim: SimConfig | None = None
    source: Annotated[str, NOT_A_KEY] = "rig.toml"   # where it was loaded from

    def camera(self, cam_id: str) -> CameraConfig:
        for cam in self.cameras:
            if cam.id == cam_id:
                return cam
        raise KeyError(cam_id)


def rig_from_dict(doc: dict, source: str = "rig.toml") -> RigConfig:
    """Validate a parsed rig.toml; raise ConfigError naming the key at the first problem.

    The keys of the [rig] table sit beside the other tables in RigConfig, so they are named
    without a prefix ("fps", "cameras[1].width", "leds.port").
    """
    if "rig" not in doc:
        raise ConfigError(f"{source}: rig: missing (the [rig] table names the rig)")
    if not isinstance(doc["rig"], dict):
        raise ConfigError(f"{source}: rig: expected a table")
    if not doc.get("cameras"):
        raise ConfigError(f"{source}: cameras: missing (at least one [[cameras]] entry)")
    rig = validate(RigConfig, {**doc["rig"], **{k: v for k, v in doc.items() if k != "rig"}}, source, ConfigError)
    ids: dict[str, int] = {}
    devices: dict[tuple[str, str], int] = {}
    for i, cam in enumerate(rig.cameras):
        if cam.id in ids:
            raise ConfigError(f"{source}: cameras[{i}].id: duplicate camera id {cam.id!r} (also cameras[{ids[cam.id]}])")
        ids[cam.id] = i
        if PLACEHOLDER in cam.device:
            raise ConfigError(f"{source}: cameras[{i}].device: {cam.device!r} is a placeholder: give the camera's "
                              "serial number or /dev/v4l/by-id path (`manus-capture rig list` shows them)")
        if (cam.backend, cam.device) in devices:
            raise ConfigError(f"{source}: cameras[{i}].device: {cam.device!r} is also the device of "
                              f"cameras[{devices[cam.backend, cam.device]}]; each camera needs its own")
        devices[cam.backend, cam.device] = i
        if cam.backend == "sim":
            _check_sim_camera(cam.sim, f"{source}: cameras[{i}].sim")
    sim = rig.sim or (SimConfig() if "sim" in {c.backend for c in rig.cameras} else None)
    if sim is not None and sim.tags_per_wall and sim.tag_size >= sim.cube_edge / sim.tags_per_wall:
        raise ConfigError(f"{source}: sim.tag_size: {sim.tag_size:g} m tags do not fit {sim.tags_per_wall} to a "
                          f"{sim.cube_edge:g} m wall (must be < {sim.cube_edge / sim.tags_per_wall:.3g} m)")
    return dataclasses.replace(rig, source=source, sim=sim)


def _check_sim_camera(sim: SimCameraConfig | None, where: str) -> None:
    """A simulated camera's pose: present, looking somewhere, and `up` not along its view."""
    if sim is None:
        raise ConfigError(f"{where}: missing (a sim camera needs its pose)")
    view = np.subtract(sim.look_at, sim.position)
    if np.linalg.norm(view) < 1e-6:
        raise ConfigError(f"{where}.look_at: must differ from the camera's position, got {list(sim.look_at)}")
    if np.linalg.norm(np.cross(view / np.linalg.norm(view), sim.up)) < 1e-6 * max(np.linalg.norm(sim.up), 1.0):
        raise ConfigError(f"{where}.up: must be neither zero nor along the viewing direction, got {list(sim.up)}")


def load_rig(path: str | Path) -> RigConfig:
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    except (IsADirectoryError, PermissionError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read ({exc.__class__.__name__})") from None
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    return rig_from_dict(doc, str(path))


def _table(record: Any) -> dict[str, Any]:
    """A record's keys as TOML writes them: TOML has no null, so unset tables are left out."""
    return {k: v for k, v in dataclasses.asdict(record).items() if v is not None}


def rig_to_dict(rig: RigConfig) -> dict[str, Any]:
    """The TOML tables of a rig: [rig], [storage], [leds], [sim] and [[cameras]]."""
    top = {f.name: getattr(rig, f.name) for f in dataclasses.fields(rig)
           if f.name not in ("cameras", "storage", "leds", "sim", "source")}
    tables = {name: _table(getattr(rig, name)) for name in ("storage", "leds", "sim") if getattr(rig, name) is not None}
    return {"rig": top, **tables, "cameras": [_table(cam) for cam in rig.cameras]}


def rig_to_toml(rig: RigConfig) -> str:
    """The TOML text of a rig; load_rig(rig_to_toml(rig)) gives back an equal rig."""
    return "# manus-capture rig configuration (docs/rig-toml.md)\n" + tomli_w.dumps(rig_to_dict(rig))
