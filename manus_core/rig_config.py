"""rig.toml: the rig's configuration, as frozen dataclasses validated on load.

The rig layer owns its configuration (the recorder reads it and `rig` never imports
`manus_capture`). Every error names the file, the key and what is wrong, in one line.
"""

from __future__ import annotations

import dataclasses
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal
from manus_core.errors import ConfigError

BACKENDS = ("sim", "v4l2", "aravis")
SYNC_MODES = ("free-run", "software-trigger", "hardware-trigger")


@dataclass(frozen=True)
class SimCameraConfig:
    """Per-camera parameters of the simulated backend; `rig init` writes realized values."""

    position: tuple[float, float, float]  # camera centre, world frame, metres
    look_at: tuple[float, float, float] = (0.0, 0.0, 0.0)
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    hfov_deg: float = 70.0
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    clock_offset_ms: float = 0.0      # device clock minus host clock at the take's start
    drift_ppm: float = 0.0            # device clock rate error
    phase_ms: float = 0.0             # free-run: first mid-exposure after the nominal tick
    timestamp_jitter_us: float = 0.0  # noise on the device timestamp
    trigger_latency_us: float = 0.0   # triggered: mean delay trigger -> mid-exposure
    trigger_jitter_us: float = 0.0
    latency_ms: float = 2.0           # mid-exposure -> host arrival (readout + transfer), mean
    latency_jitter_ms: float = 0.2
    drop_rate: float = 0.0            # probability that a frame never reaches the host


@dataclass(frozen=True)
class CameraConfig:
    id: str
    backend: Literal["sim", "v4l2", "aravis"]
    device: str                       # serial number, /dev/v4l/by-id path, or sim:N
    width: int = 1280
    height: int = 720
    fps: float = 120.0
    pixel_format: str = "MJPG"
    exposure_us: float = 2000.0
    gain_db: float = 0.0
    sim: SimCameraConfig | None = None


@dataclass(frozen=True)
class LedConfig:
    port: str                         # serial port, or "sim" for the simulated controller
    protocol: Literal["ascii", "dmx", "sim"] = "ascii"
    panels: int = 6
    baudrate: int = 115200
    level: float = 1.0                # default level, 0..1


@dataclass(frozen=True)
class StorageConfig:
    root: str = "sessions"
    min_free_gb: float = 1.0
    jpeg_quality: int = 90            # for backends that hand out raw frames
    # "444" keeps colour at full resolution: the paint key and the hand/object colour models decide
    # the pixels along small painted spots on colour (paint and skin are close in brightness), and
    # 4:2:0 halves colour resolution for about 25 % smaller frames
    jpeg_chroma: Literal["444", "420"] = "444"

    def jpeg_params(self) -> list[int]:
        """cv2.imencode parameters of the stored JPEG frames."""
        import cv2

        sampling = {"444": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444, "420": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420}
        return [cv2.IMWRITE_JPEG_QUALITY, int(self.jpeg_quality),
                cv2.IMWRITE_JPEG_SAMPLING_FACTOR, sampling[self.jpeg_chroma]]


@dataclass(frozen=True)
class SimConfig:
    """The simulated world; the per-camera clock and optics live in each camera's `sim` table."""

    cube_edge: float = 1.2
    tag_size: float = 0.24
    tags_per_wall: int = 3
    subject: str = "s01"
    object: Literal["box", "mug", "sphere"] = "mug"
    paint: bool = False
    time_scale: float = 0.0           # 0: as fast as rendering allows (virtual clock); 1: real time
    noise_sigma: float = 2.0          # image noise, grey levels
    supersample: int = 2              # anti-aliasing of the hand, object and table edges
    seed: int = 0


@dataclass(frozen=True)
class RigConfig:
    name: str
    cameras: tuple[CameraConfig, ...]
    layout: str = "custom"
    fps: float = 120.0
    sync: Literal["free-run", "software-trigger", "hardware-trigger"] = "free-run"
    leds: LedConfig | None = None
    storage: StorageConfig = field(default_factory=StorageConfig)
    sim: SimConfig | None = None
    source: str = "rig.toml"          # where it was loaded from; not a TOML key

    def camera(self, cam_id: str) -> CameraConfig:
        for cam in self.cameras:
            if cam.id == cam_id:
                return cam
        raise KeyError(cam_id)


def _type_name(tp) -> str:
    return getattr(tp, "__name__", str(tp))


def _convert(value, tp, where: str, source: str):
    """Check `value` against the annotation `tp`; return it converted (lists to tuples)."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        return _convert(value, inner[0], where, source)
    if origin is Literal:
        if value not in args:
            choices = ", ".join(repr(a) for a in args)
            raise ConfigError(f"{source}: {where}: {value!r} is not one of {choices}")
        return value
    if origin is tuple:
        if not isinstance(value, list):
            raise ConfigError(f"{source}: {where}: expected an array, got {type(value).__name__}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(v, args[0], f"{where}[{i}]", source) for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"{source}: {where}: expected {len(args)} values, got {len(value)}")
        return tuple(_convert(v, a, f"{where}[{i}]", source) for i, (v, a) in enumerate(zip(value, args)))
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{source}: {where}: expected a table, got {type(value).__name__}")
        return _build(tp, value, where, source)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{source}: {where}: expected a number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{source}: {where}: expected an integer, got {value!r}")
        return value
    if not isinstance(value, tp):
        raise ConfigError(f"{source}: {where}: expected {_type_name(tp)}, got {value!r}")
    return value


def _build(cls, table: dict, where: str, source: str):
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.name != "source"}
    unknown = sorted(set(table) - names)
    if unknown:
        prefix = f"{where}." if where else ""
        raise ConfigError(f"{source}: {prefix}{unknown[0]}: unknown key (known: {', '.join(sorted(names))})")
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name == "source":
            continue
        key = f"{where}.{f.name}" if where else f.name
        if f.name not in table:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(f"{source}: {key}: missing")
            continue
        kwargs[f.name] = _convert(table[f.name], hints[f.name], key, source)
    return cls(**kwargs)


def rig_from_dict(doc: dict, source: str = "rig.toml") -> RigConfig:
    """Validate a parsed rig.toml; raise ConfigError naming the key at the first problem."""
    if "rig" not in doc:
        raise ConfigError(f"{source}: rig: missing (the [rig] table names the rig)")
    top = dict(doc["rig"]) if isinstance(doc["rig"], dict) else doc["rig"]
    if not isinstance(top, dict):
        raise ConfigError(f"{source}: rig: expected a table")
    extra = sorted(set(doc) - {"rig", "cameras", "leds", "storage", "sim"})
    if extra:
        raise ConfigError(f"{source}: {extra[0]}: unknown table")
    cams = doc.get("cameras")
    if not cams:
        raise ConfigError(f"{source}: cameras: missing (at least one [[cameras]] entry)")
    for i, cam in enumerate(cams):
        if isinstance(cam, dict) and "backend" in cam and cam["backend"] not in BACKENDS:
            raise ConfigError(f"{source}: cameras[{i}].backend: unknown backend {cam['backend']!r} "
                              f"(known: {', '.join(BACKENDS)})")
    merged = {**top, "cameras": cams, **{k: doc[k] for k in ("leds", "storage", "sim") if k in doc}}
    rig = _build(RigConfig, merged, "", source)
    object.__setattr__(rig, "source", source)
    seen: dict[str, int] = {}
    for i, cam in enumerate(rig.cameras):
        if cam.id in seen:
            raise ConfigError(f"{source}: cameras[{i}].id: duplicate camera id {cam.id!r} "
                              f"(also cameras[{seen[cam.id]}])")
        seen[cam.id] = i
        if cam.backend == "sim" and cam.sim is None:
            raise ConfigError(f"{source}: cameras[{i}].sim: missing (a sim camera needs its pose)")
        if cam.width <= 0 or cam.height <= 0 or cam.fps <= 0:
            raise ConfigError(f"{source}: cameras[{i}]: width, height and fps must be positive")
    if any(c.backend == "sim" for c in rig.cameras) and rig.sim is None:
        object.__setattr__(rig, "sim", SimConfig())
    return rig


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


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (tuple, list)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(type(v))


def _table_lines(obj) -> list[str]:
    return [f"{f.name} = {_toml_value(getattr(obj, f.name))}" for f in dataclasses.fields(obj)
            if not dataclasses.is_dataclass(getattr(obj, f.name)) and getattr(obj, f.name) is not None
            and f.name not in ("cameras", "source")]


def rig_to_toml(rig: RigConfig) -> str:
    """The TOML text of a rig; load_rig(rig_to_toml(rig)) gives back an equal rig."""
    lines = ["# manus-capture rig configuration (docs/rig-toml.md)", "[rig]", *_table_lines(rig), ""]
    for name in ("storage", "leds", "sim"):
        table = getattr(rig, name)
        if table is not None:
            lines += [f"[{name}]", *_table_lines(table), ""]
    for cam in rig.cameras:
        lines += ["[[cameras]]", *_table_lines(cam), ""]
        if cam.sim is not None:
            lines += ["[cameras.sim]", *_table_lines(cam.sim), ""]
    return "\n".join(lines)
