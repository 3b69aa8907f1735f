"""DATASET.h5: the annotations of many takes, one group per take (DESIGN.md, "On disk").

    with DatasetWriter("DATASET.h5") as w:           # resumable: w.done lists finished takes
        w.add(annotation)                            # one TakeAnnotation, saved at once
    ds = read_dataset("DATASET.h5")                  # Dataset: ds.takes, ds[key] -> TakeAnnotation

Layout (docs/annotate.md has every field):

    /                      attrs: format = "manus-capture dataset", version = 1, software
    /SESSION/TAKE/         one group per take (the key is "SESSION/TAKE", so that takes of many
                           sessions with the same names can live in one file)
        frame_ns (T) int64, frame_index (T,C) int64 (-1: no frame), keypoints2d (T,C,21,3) float32,
        keypoints3d (T,21,3), keypoints3d_error_px (T,21), keypoints3d_views (T,21) int16,
        joint_angles_raw (T,26), joint_angles (T,26), bone_lengths (20), ik_residual_m (T),
        flags (T) uint8 (FLAGS)
        attrs: cameras, kind, take, skeleton (JSON), calibration, calibration_sha256, software,
               keypoint_source, bone_source, filter (JSON), flags (JSON legend), status

Writing is resumable and atomic. Each finished take is first saved on its own, atomically, as a
part file in a folder beside the output (`.DATASET.h5.parts/`); `finalize` then builds the whole
file under a temporary name (the groups of an existing DATASET.h5 that are not being replaced,
then the parts), fsyncs it and renames it over the output, and removes the parts. A run that is
interrupted leaves the finished takes in the parts folder (and the old output untouched), and the
next run picks them up instead of computing them again. Nothing is ever half-written under the
final name.
"""

from __future__ import annotations

import io
import json
import shutil
from collections.abc import Iterator
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import h5py
import numpy as np

from manus_core.errors import DatasetError
from manus_core.fileio import atomic_output, write_atomic
from manus_core.skeleton import DOF_NAMES, JOINT_NAMES, HandSkeleton

FORMAT = "manus-capture dataset"
VERSION = 1
# Per-frame flags (bit values), also written as a JSON legend into every take's attributes.
FLAGS = {
    "no_hand": 1,           # fewer joints triangulated than IK needs: angles NaN
    "missing_joints": 2,    # some joints not triangulated (too few views or outliers)
    "ik_poor": 4,           # IK residual above the take's threshold
    "incomplete_group": 8,  # some cameras have no frame in this group
}
_ARRAYS = {  # name: (dtype, compress in frame chunks)
    "frame_ns": (np.int64, True), "frame_index": (np.int64, True), "keypoints2d": (np.float32, True),
    "keypoints3d": (np.float64, True), "keypoints3d_error_px": (np.float32, True),
    "keypoints3d_views": (np.int16, True), "joint_angles_raw": (np.float64, True),
    "joint_angles": (np.float64, True), "bone_lengths": (np.float64, False),
    "ik_residual_m": (np.float32, True), "flags": (np.uint8, True),
}
_JSON_ATTRS = ("skeleton", "filter", "flags")


def software_version() -> str:
    try:
        return f"manus-capture {version('manus-capture')}"
    except PackageNotFoundError:
        return "manus-capture (not installed)"


def skeleton_description(skeleton: HandSkeleton) -> dict:
    """What the joint angles mean: the skeleton's name, joint and DOF order and limits."""
    return {"name": "manus-capture 26-DOF hand (MediaPipe joint order)", "joint_names": list(JOINT_NAMES),
            "dof_names": list(DOF_NAMES), "lower": [None if not np.isfinite(x) else float(x) for x in skeleton.lower],
            "upper": [None if not np.isfinite(x) else float(x) for x in skeleton.upper],
            "rotation": "rotation vector, hand frame to world", "units": "m, rad"}


@dataclass
class TakeAnnotation:
    """One take's annotations (the arrays of a DATASET.h5 take group) and its attributes."""

    key: str
    cameras: tuple[str, ...]
    frame_ns: np.ndarray
    frame_index: np.ndarray
    keypoints2d: np.ndarray
    keypoints3d: np.ndarray
    keypoints3d_error_px: np.ndarray
    keypoints3d_views: np.ndarray
    joint_angles_raw: np.ndarray
    joint_angles: np.ndarray
    bone_lengths: np.ndarray
    ik_residual_m: np.ndarray
    flags: np.ndarray
    attrs: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        n_t, n_c = len(self.frame_ns), len(self.cameras)
        shapes = {"frame_index": (n_t, n_c), "keypoints2d": (n_t, n_c, 21, 3), "keypoints3d": (n_t, 21, 3),
                  "keypoints3d_error_px": (n_t, 21), "keypoints3d_views": (n_t, 21), "joint_angles_raw": (n_t, 26),
                  "joint_angles": (n_t, 26), "bone_lengths": (20,), "ik_residual_m": (n_t,), "flags": (n_t,)}
        for name, shape in shapes.items():
            value = np.asarray(getattr(self, name))
            if value.shape != shape:
                raise DatasetError(f"take {self.key}: {name} has shape {value.shape}, expected {shape}")

    def fitted_joints(self, filtered: bool = True) -> np.ndarray:
        """Joints (T,21,3) of the skeleton posed by the (filtered or raw) joint angles."""
        angles = self.joint_angles if filtered else self.joint_angles_raw
        return HandSkeleton(self.bone_lengths).forward(angles)


def _write_group(group, ann: TakeAnnotation) -> None:
    n_t = len(ann.frame_ns)
    for name, (dtype, chunked) in _ARRAYS.items():
        data = np.asarray(getattr(ann, name), dtype=dtype)
        opts = {}
        if chunked and n_t > 0:
            rows = max(1, min(n_t, (1 << 20) // max(data[0].nbytes, 1)))   # about 1 MB per chunk
            opts = {"chunks": (rows,) + data.shape[1:], "compression": "gzip", "compression_opts": 4,
                    "shuffle": True}
        group.create_dataset(name, data=data, **opts)
    attrs = dict(ann.attrs)
    attrs["cameras"] = list(ann.cameras)
    attrs.setdefault("flags", FLAGS)
    for key, value in attrs.items():
        group.attrs[key] = json.dumps(value) if key in _JSON_ATTRS and not isinstance(value, str) else value


def _read_group(group, key: str) -> TakeAnnotation:
    missing = [name for name in _ARRAYS if name not in group]
    if missing:
        raise DatasetError(f"take {key}: missing {', '.join(missing)}")
    arrays = {name: group[name][()] for name in _ARRAYS}
    attrs = {}
    for name, value in group.attrs.items():
        if isinstance(value, bytes):
            value = value.decode()
        if name in _JSON_ATTRS and isinstance(value, str):
            value = json.loads(value)
        elif isinstance(value, np.ndarray):
            value = [v.decode() if isinstance(v, bytes) else v for v in value.tolist()]
        attrs[name] = value
    cameras = tuple(str(c) for c in attrs.pop("cameras", []))
    return TakeAnnotation(key, cameras, attrs=attrs, **arrays)


def _take_keys(f) -> list[str]:
    """Keys of the take groups (groups holding frame_ns), at any depth."""
    keys: list[str] = []

    def visit(name, obj):
        if isinstance(obj, h5py.Group) and "frame_ns" in obj:
            keys.append(name)

    f.visititems(visit)
    return sorted(keys)


def _check_format(f, path: Path) -> None:
    if f.attrs.get("format") != FORMAT:
        raise DatasetError(f"{path}: not a manus-capture dataset (format attribute {f.attrs.get('format')!r})")
    if int(f.attrs.get("version", -1)) > VERSION:
        raise DatasetError(f"{path}: dataset version {f.attrs.get('version')} is newer than this software reads "
                           f"({VERSION})")


def _open(path: Path):
    try:
        return h5py.File(path, "r")
    except FileNotFoundError:
        raise DatasetError(f"{path}: no such dataset file") from None
    except OSError as exc:
        raise DatasetError(f"{path}: cannot be read as HDF5 ({exc})") from None


class Dataset:
    """A DATASET.h5 opened for reading; takes are read on access."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        with _open(self.path) as f:
            _check_format(f, self.path)
            self.attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
            self.takes: list[str] = _take_keys(f)

    def __len__(self) -> int:
        return len(self.takes)

    def __iter__(self) -> Iterator[str]:
        return iter(self.takes)

    def __contains__(self, key: object) -> bool:
        return key in self.takes

    def __getitem__(self, key: str) -> TakeAnnotation:
        if key not in self.takes:
            raise KeyError(f"{self.path}: no take {key!r} (takes: {', '.join(self.takes) or 'none'})")
        with _open(self.path) as f:
            return _read_group(f[key], key)


def read_dataset(path: str | Path) -> Dataset:
    """Open a DATASET.h5 for reading (DatasetError names the file when it is not one)."""
    return Dataset(path)


def _part_name(key: str) -> str:
    return key.replace("/", "__") + ".h5"


def _new_file_attrs(f) -> None:
    f.attrs.update({"format": FORMAT, "version": VERSION, "software": software_version()})


class DatasetWriter:
    """Builds DATASET.h5 take by take, resumably (see the module doc).

    force=True starts over: an existing output's takes and any saved parts are not reused (the old
    output stays in place until finalize replaces it).
    """

    def __init__(self, path: str | Path, force: bool = False) -> None:
        self.path = Path(path)
        self.parts = self.path.parent / f".{self.path.name}.parts"
        self.force = force
        if force and self.parts.exists():
            shutil.rmtree(self.parts)
        self.existing: list[str] = []
        if self.path.exists() and not force:
            with _open(self.path) as f:
                _check_format(f, self.path)
                self.existing = _take_keys(f)

    @property
    def saved(self) -> list[str]:
        """Keys of the takes saved as parts (finished, not yet in the output)."""
        keys = []
        for part in sorted(self.parts.glob("*.h5")) if self.parts.is_dir() else []:
            try:
                with h5py.File(part, "r") as f:
                    keys.append(str(f.attrs["key"]))
            except (OSError, KeyError):
                part.unlink()   # cannot happen with atomic writes unless edited by hand: redo that take
        return keys

    @property
    def done(self) -> set[str]:
        """Takes that need no work: in the output already, or saved as parts."""
        return set(self.existing) | set(self.saved)

    def add(self, ann: TakeAnnotation) -> Path:
        """Save one finished take, atomically, as a part file."""
        buffer = io.BytesIO()
        with h5py.File(buffer, "w") as f:
            _new_file_attrs(f)
            f.attrs["key"] = ann.key
            _write_group(f.create_group("take"), ann)
        target = self.parts / _part_name(ann.key)
        write_atomic(target, buffer.getvalue())
        return target

    def finalize(self) -> list[str]:
        """Write the output (existing takes not replaced + all parts) atomically; returns its takes."""
        parts = sorted(self.parts.glob("*.h5")) if self.parts.is_dir() else []
        keys: list[str] = []
        with atomic_output(self.path) as tmp, h5py.File(tmp, "w") as out:
            _new_file_attrs(out)
            new = {}
            for part in parts:
                with h5py.File(part, "r") as f:
                    new[str(f.attrs["key"])] = part
            if self.existing and not self.force:
                with h5py.File(self.path, "r") as old:
                    for key in self.existing:
                        if key not in new:
                            _copy(old, key, out, key)
                            keys.append(key)
            for key, part in new.items():
                with h5py.File(part, "r") as f:
                    _copy(f, "take", out, key)
                keys.append(key)
        if self.parts.is_dir():
            shutil.rmtree(self.parts)
        self.existing, self.force = sorted(keys), False
        return self.existing

    def __enter__(self) -> "DatasetWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        # Only a clean exit writes the output; after an error the parts stay for the next run.
        if exc_type is None:
            self.finalize()


def _copy(src, src_name: str, dst, dst_key: str) -> None:
    parent, _, name = dst_key.rpartition("/")
    target = dst.require_group(parent) if parent else dst
    src.copy(src[src_name], target, name=name)


def add_arrays(path: str | Path, key: str, arrays: dict[str, np.ndarray], attrs: dict | None = None) -> None:
    """Add (or replace) arrays of take `key` in DATASET.h5, gzip-compressed, atomically: a copy of
    the file is changed and renamed over it. Later stages (segment, contacts) add to the takes
    that annotate wrote; a crash leaves the old file whole."""
    path = Path(path)
    with atomic_output(path) as tmp:
        if path.exists():
            shutil.copyfile(path, tmp)
        with h5py.File(tmp, "a") as f:
            if "format" not in f.attrs:
                _new_file_attrs(f)
            group = f.require_group(key)
            for name, data in arrays.items():
                data = np.asarray(data)
                if name in group:
                    del group[name]
                chunks = (1,) + data.shape[1:] if data.ndim >= 3 else None
                group.create_dataset(name, data=data, compression="gzip", compression_opts=4, chunks=chunks)
            for k, v in (attrs or {}).items():
                group.attrs[k] = v
