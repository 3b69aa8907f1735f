"""DATASET.h5: the results of many takes, one group per take (DESIGN.md, "On disk").

    with DatasetWriter("DATASET.h5") as w:    # resumable: w.done lists the annotated takes,
        w.add(annotation)                     # w.inputs(key) what made one; one TakeAnnotation, saved at once
    ds = read_dataset("DATASET.h5")           # Dataset: ds.takes (any stage), ds.annotated
    ds[key]                                   # -> TakeAnnotation (DatasetError: the take has no annotation)
    ds.stages(key)                            # {"annotate", "segment", "contacts"}: what the take holds
    ds.provenance(key, "segment")             # the inputs that made those results (None: not recorded)
    add_arrays(path, key, arrays, attrs, stage="segment")    # how a later stage adds its part

Layout (docs/annotate.md has every field):

    /                      attrs: format = "manus-capture dataset", version = 1, software
    /SESSION/TAKE/         one group per take (the key is "SESSION/TAKE", so that takes of many
                           sessions with the same names can live in one file)
        frame_ns (T) int64, frame_index (T,C) int64 (-1: no frame), keypoints2d (T,C,21,3) float32,
        keypoints3d (T,21,3), keypoints3d_error_px (T,21), keypoints3d_views (T,21) int16,
        joint_angles_raw (T,26), joint_angles (T,26), bone_lengths (20), ik_residual_m (T),
        flags (T) uint8 (FLAGS)
        attrs: cameras, kind, take, skeleton (JSON), calibration, calibration_sha256, software,
               keypoint_source, bone_source, filter (JSON), flags (JSON legend), status,
               cameras_left_out, provenance_annotate (JSON: manus_core.provenance)
        masks/, paint/ (segment), contacts/ (contacts), with their own attrs and provenance_STAGE

Stages own their parts of a take group (provenance.STAGE_ARRAYS): a take may hold any of them, so
a reader asks `ds.stages(key)` before it reads one; `ds[key]` (the annotation) raises DatasetError
for a take that has none. The writer replaces only annotate's arrays and attributes of a take and
copies the rest over unchanged: a take re-annotated after it was re-recorded keeps its masks and
contacts, whose own provenance then no longer matches the take (their readers say so) until
segment and contacts run again.

Writing is resumable and atomic. Each finished take is first saved on its own, atomically, as a
part file in a folder beside the output (`.DATASET.h5.parts/`); `finalize` then builds the whole
file under a temporary name (the groups of an existing DATASET.h5 that are not being replaced,
then the parts), fsyncs it and renames it over the output, and removes the parts. A run that is
interrupted leaves the finished takes in the parts folder (and the old output untouched), and the
next run picks them up instead of computing them again. Nothing is ever half-written under the
final name. Whether a take's annotation may be reused is the caller's decision: `inputs(key)` gives
what made it, and annotate compares it with what would make it now (provenance.differences).
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

from manus_core.errors import DatasetError, OutputError
from manus_core.fileio import atomic_output, write_atomic
from manus_core.provenance import STAGE_ARRAYS, differences, read_provenance
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
TAKE_MARK = "manus_take"   # attribute of every take group: what is a take does not depend on its name
# The take attributes annotate writes: replaced (or removed) when annotate redoes a take.
ANNOTATION_ATTRS = ("cameras", "kind", "take", "skeleton", "calibration", "calibration_sha256", "software",
                    "keypoint_source", "bone_source", "filter", "flags", "status", "frame_groups",
                    "cameras_left_out", "provenance_annotate")


def take_key(path: Path) -> str:
    """The take's group in DATASET.h5: SESSION/TAKE (folder names)."""
    path = Path(path).resolve()
    return f"{path.parent.name}/{path.name}"


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
    group.attrs[TAKE_MARK] = True
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


def _stages(group) -> set[str]:
    return {stage for stage, names in STAGE_ARRAYS.items() if any(name in group for name in names)}


def _take_stages(f) -> dict[str, set[str]]:
    """The take groups (groups holding any stage's results, at any depth; what is inside a take
    group is never taken for another take) and the stages each holds."""
    found: dict[str, set[str]] = {}

    def walk(group) -> None:
        for item in group.values():
            if not isinstance(item, h5py.Group):
                continue
            # Files written before take groups were marked: a group holding a stage's results is
            # a take, unless one of its own groups is marked (a take folder named "masks", say).
            marked = item.attrs.get(TAKE_MARK) or (
                not any(isinstance(c, h5py.Group) and c.attrs.get(TAKE_MARK) for c in item.values())
                and _stages(item))
            if marked:
                found[item.name.lstrip("/")] = _stages(item)
            else:
                walk(item)

    walk(f)
    return dict(sorted(found.items()))


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
    """A DATASET.h5 opened for reading; takes are read on access.

    `takes` lists every take with any stage's results; `stages(key)` says which ("annotate",
    "segment", "contacts", "refine"), `annotated` the takes that `ds[key]` can read."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        with _open(self.path) as f:
            _check_format(f, self.path)
            self.attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
            self._stages = _take_stages(f)
        self.takes: list[str] = list(self._stages)

    def __len__(self) -> int:
        return len(self.takes)

    def __iter__(self) -> Iterator[str]:
        return iter(self.takes)

    def __contains__(self, key: object) -> bool:
        return key in self.takes

    @property
    def annotated(self) -> list[str]:
        """The takes with annotate's results (the ones ds[key] reads)."""
        return [key for key in self.takes if "annotate" in self._stages[key]]

    def stages(self, key: str) -> set[str]:
        """The stages whose results take `key` holds (a subset of provenance.STAGE_ARRAYS)."""
        self._check_key(key)
        return set(self._stages[key])

    def provenance(self, key: str, stage: str) -> dict | None:
        """The inputs that made `stage`'s results of take `key` (None: not recorded)."""
        self._check_key(key)
        with _open(self.path) as f:
            return read_provenance(f[key], stage)

    def recording_differences(self, key: str, stage: str, inputs: dict | None = None) -> list[str]:
        """Why take `key`'s annotation and the results of `stage` (or, given `inputs`, the results
        those inputs make) are not of the same recording: the take was re-recorded between them
        ([] when they are, or when either does not record it)."""
        own = self.provenance(key, stage) if inputs is None else inputs
        annotation = self.provenance(key, "annotate") if "annotate" in self.stages(key) else None
        if not own or not annotation or "take" not in own or "take" not in annotation:
            return []
        return differences({"take": annotation["take"]}, {"take": own["take"]})

    def __getitem__(self, key: str) -> TakeAnnotation:
        self._check_key(key)
        if "annotate" not in self._stages[key]:
            raise DatasetError(f"{self.path}: take {key} has no annotation, only the results of "
                               f"{', '.join(sorted(self._stages[key]))} (run annotate on it)")
        with _open(self.path) as f:
            return _read_group(f[key], key)

    def pose_angles(self, key: str) -> tuple[np.ndarray, str]:
        """The joint angles (T,26) the later stages use, and which they are: refine's
        `joint_angles_refined` when the take has them, else annotate's filtered `joint_angles`."""
        ann = self[key]
        if "refine" in self._stages[key]:
            with _open(self.path) as f:
                refined = f[key]["joint_angles_refined"][()]
            if refined.shape == ann.joint_angles.shape:
                return refined, "joint_angles_refined"
        return ann.joint_angles, "joint_angles"

    def _check_key(self, key: str) -> None:
        if key not in self.takes:
            raise KeyError(f"{self.path}: no take {key!r} (takes: {', '.join(self.takes) or 'none'})")


def read_dataset(path: str | Path) -> Dataset:
    """Open a DATASET.h5 for reading (DatasetError names the file when it is not one)."""
    return Dataset(path)


def _part_name(key: str) -> str:
    return key.replace("/", "__") + ".h5"


def _new_file_attrs(f) -> None:
    f.attrs.update({"format": FORMAT, "version": VERSION, "software": software_version()})


class DatasetWriter:
    """Builds DATASET.h5 take by take, resumably (see the module doc).

    force=True does not reuse the parts of an interrupted run. Takes of the output that are not
    added again, and the other stages' results of those that are, are always kept.
    """

    def __init__(self, path: str | Path, force: bool = False) -> None:
        self.path = Path(path)
        self.parts = self.path.parent / f".{self.path.name}.parts"
        if force and self.parts.exists():
            shutil.rmtree(self.parts)
        self.existing: dict[str, set[str]] = {}
        if self.path.exists():
            with _open(self.path) as f:
                _check_format(f, self.path)
                self.existing = _take_stages(f)

    @property
    def saved(self) -> list[str]:
        """Keys of the takes saved as parts (finished, not yet in the output)."""
        return list(self._parts())

    def _parts(self) -> dict[str, Path]:
        found = {}
        for part in sorted(self.parts.glob("*.h5")) if self.parts.is_dir() else []:
            try:
                with h5py.File(part, "r") as f:
                    found[str(f.attrs["key"])] = part
            except (OSError, KeyError):
                part.unlink()   # cannot happen with atomic writes unless edited by hand: redo that take
        return found

    @property
    def done(self) -> set[str]:
        """Takes that have an annotation: in the output already, or saved as parts."""
        return {k for k, stages in self.existing.items() if "annotate" in stages} | set(self.saved)

    def inputs(self, key: str) -> dict | None:
        """The inputs recorded with take `key`'s annotation (its saved part first, then the
        output); None when it has none or they were not recorded."""
        part = self._parts().get(key)
        if part is not None:
            with h5py.File(part, "r") as f:
                return read_provenance(f["take"], "annotate")
        if "annotate" not in self.existing.get(key, ()):
            return None
        with _open(self.path) as f:
            return read_provenance(f[key], "annotate")

    def add(self, ann: TakeAnnotation) -> Path:
        """Save one finished take, atomically, as a part file."""
        buffer = io.BytesIO()
        with h5py.File(buffer, "w") as f:
            _new_file_attrs(f)
            f.attrs["key"] = ann.key
            _write_group(f.create_group("take"), ann)
        target = self.parts / _part_name(ann.key)
        try:
            write_atomic(target, buffer.getvalue())
        except OutputError as exc:
            reason = str(exc).rpartition("cannot write: ")[2]
            raise OutputError(f"{self.path}: take {ann.key}: cannot write: {reason}") from exc
        return target

    def finalize(self) -> list[str]:
        """Write the output (its takes, each part's annotation replacing annotate's arrays and
        attributes of its take) atomically; returns its takes."""
        new = self._parts()
        try:
            self._write(new)
        except OutputError as exc:
            if new:
                raise OutputError(f"{exc}; the {len(new)} finished take(s) stay in {self.parts} and the next "
                                  f"run adds them") from exc
            raise
        if self.parts.is_dir():
            shutil.rmtree(self.parts)
        return list(self.existing)

    def _write(self, new: dict[str, Path]) -> None:
        with atomic_output(self.path) as tmp, h5py.File(tmp, "w") as out:
            _new_file_attrs(out)
            old = h5py.File(self.path, "r") if self.existing else None
            try:
                for key in self.existing:
                    if key not in new:
                        _copy(old[key], out, key)
                for key, part in new.items():
                    with h5py.File(part, "r") as f:
                        group = _copy(f["take"], out, key)
                    if key in self.existing:
                        _keep_other_stages(old[key], group)
            finally:
                if old is not None:
                    old.close()
            self.existing = _take_stages(out)

    def __enter__(self) -> "DatasetWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        # Only a clean exit writes the output; after an error the parts stay for the next run.
        if exc_type is None:
            self.finalize()


def _copy(src, dst, dst_key: str):
    parent, _, name = dst_key.rpartition("/")
    target = dst.require_group(parent) if parent else dst
    target.copy(src, target, name=name)
    return target[name]


def _keep_other_stages(old, group) -> None:
    """Copy into a take's new annotation `group` what the other stages wrote into its `old` group."""
    for name in old:
        if name not in STAGE_ARRAYS["annotate"]:
            old.copy(old[name], group, name=name)
    for name, value in old.attrs.items():
        if name not in ANNOTATION_ATTRS and name not in group.attrs:
            group.attrs[name] = value


def add_arrays(path: str | Path, key: str, arrays: dict[str, np.ndarray | h5py.Dataset], attrs: dict | None = None,
               stage: str | None = None) -> None:
    """Add (or replace) arrays of take `key` in DATASET.h5, gzip-compressed, atomically: a copy of
    the file is changed and renamed over it. Later stages (segment, contacts) add to the takes
    that annotate wrote (or to a take of their own); a crash leaves the old file whole.

    stage: the stage writing; an array outside its part of the take (provenance.STAGE_ARRAYS) is
    refused with DatasetError before anything is written, so no stage overwrites another's, and
    the stage's part is replaced whole (what an earlier run wrote and this one does not is gone)."""
    path = Path(path)
    if stage is not None:
        foreign = [name for name in arrays if name.split("/")[0] not in STAGE_ARRAYS[stage]]
        if foreign:
            raise DatasetError(f"{path}: take {key}: {stage} may not write {', '.join(foreign)} "
                               f"(its part: {', '.join(STAGE_ARRAYS[stage])})")
    # The arrays are compressed in memory first and then copied: HDF5 can crash the process when
    # the disk fills up while it writes a compressed dataset, whereas a failed copy is an error.
    # An array that is already an HDF5 dataset (masks too large for memory) is copied from its file.
    staged = io.BytesIO()
    with h5py.File(staged, "w") as src:
        for name, data in arrays.items():
            if isinstance(data, h5py.Dataset):
                continue
            data = np.asarray(data)
            chunks = (1,) + data.shape[1:] if data.ndim >= 3 else None
            src.create_dataset(name, data=data, compression="gzip", compression_opts=4, chunks=chunks)
    with atomic_output(path) as tmp:
        if path.exists():
            shutil.copyfile(path, tmp)
        with h5py.File(tmp, "a") as f, h5py.File(staged, "r") as src:
            if "format" not in f.attrs:
                _new_file_attrs(f)
            group = f.require_group(key)
            group.attrs[TAKE_MARK] = True
            for name in STAGE_ARRAYS[stage] if stage is not None else ():
                if name in group:   # a stage's part is replaced whole: nothing of an earlier run lingers
                    del group[name]
            for name in arrays:
                if name in group:
                    del group[name]
                parent, _, leaf = name.rpartition("/")
                data = arrays[name]
                src.copy(data if isinstance(data, h5py.Dataset) else src[name],
                         group.require_group(parent) if parent else group, name=leaf)
            for k, v in (attrs or {}).items():
                group.attrs[k] = v
