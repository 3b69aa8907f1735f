"""ground_truth.h5 of a simulated take (DESIGN.md, "On disk"): its layout and its one reader.

    gt = GroundTruth.of_take("S/grasp_01")
    rig = gt.cameras.rig()                 # the exact cameras
    gt.frames.exposure_mid_ns              # (C,F) true mid-exposure of every frame (-1: not produced)
    gt.hand.joints3d                       # (F,21,3) on the rig's nominal ticks
    gt.labels([0])                         # (C,1,H,W) per-pixel truth of the first labelled tick

Each group of the file is one frozen record below: the record's array fields are the group's
datasets and its other fields the group's attributes, named as the fields are (TruthInfo is the
file's own attributes). rig.sim.ground_truth writes the file with `write_record` from these same
records, so writer and reader cannot disagree on a key. A field with a default is optional (the
simulator writes it for some takes only); a missing required one raises GroundTruthError naming
the file and the key. F indexes the rig's nominal frame ticks, C the cameras in `cameras.ids`
order; the labels are `labels/frames` (F') and `labels/image` (C,F',H,W), read per image.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import ClassVar, TypeVar

import h5py
import numpy as np

from manus_core.cameras import CameraRig
from manus_core.errors import GroundTruthError

FILE_NAME = "ground_truth.h5"
LABEL_FRAMES = "labels/frames"
LABEL_IMAGE = "labels/image"
# the classes of the label images (walls: the cube's walls and the table)
LABEL_BACKGROUND, LABEL_HAND, LABEL_OBJECT, LABEL_PAINT, LABEL_WALLS = 0, 1, 2, 3, 4
GZIP = {"compression": "gzip", "compression_opts": 4}


@dataclass(frozen=True, eq=False)
class TruthInfo:
    """The take the file is the truth of (the file's attributes)."""

    GROUP: ClassVar[str] = "/"
    kind: str
    fps: float
    sync: str
    t0_ns: int
    subject: str
    object: str
    paint: bool
    seed: int
    tags_json: str


@dataclass(frozen=True, eq=False)
class TruthCameras:
    """The true cameras: x_cam = R @ x_world + t; size (C,2) as (width, height)."""

    GROUP: ClassVar[str] = "cameras"
    ids: tuple[str, ...]
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    size: np.ndarray

    def rig(self) -> CameraRig:
        return CameraRig(self.ids, self.K, self.dist, self.R, self.t, self.size)


@dataclass(frozen=True, eq=False)
class TruthClock:
    """Each camera's clock (C,): device minus host offset and drift, frame phase and latencies."""

    GROUP: ClassVar[str] = "clock"
    offset_ns: np.ndarray
    drift_ppm: np.ndarray
    phase_ns: np.ndarray
    latency_ns: np.ndarray
    trigger_latency_ns: np.ndarray


@dataclass(frozen=True, eq=False)
class TruthFrames:
    """tick_ns (F,) the nominal ticks; exposure_mid_ns (C,F) on the host clock, -1 where the camera
    produced no frame for a tick; dropped (C,F) lost before the host saw it; led_level (F,)."""

    GROUP: ClassVar[str] = "frames"
    tick_ns: np.ndarray
    exposure_mid_ns: np.ndarray
    dropped: np.ndarray
    led_level: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class TruthHand:
    """The hand on every tick: joint_angles (F,26), joints3d (F,21,3), bone_lengths (20,), and
    rest_joints (21,3) of the rest pose, the frame of `TruthSkin`."""

    GROUP: ClassVar[str] = "hand"
    joint_angles: np.ndarray
    joints3d: np.ndarray
    bone_lengths: np.ndarray
    rest_joints: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class TruthSkin:
    """The subject's rest-pose skin, for measuring any hand model against it: points (N,3) (m, in
    the frame of `TruthHand.rest_joints`), outward normals (N,3), bone (N,) the bone each point
    follows most (bone b runs from PARENTS[b + 1] to joint b + 1), faces (T,3) of its mesh, its
    blend-skinning weights (N,20) (the skin of a frame: the weights' blend of the bones' motions,
    pressed flat where it would enter the object), and the subject's parameters as a TOML text."""

    GROUP: ClassVar[str] = "hand/rest_surface"
    points: np.ndarray
    normals: np.ndarray
    bone: np.ndarray
    faces: np.ndarray
    weights: np.ndarray
    subject_toml: str = ""


@dataclass(frozen=True, eq=False)
class TruthContact:
    """Contact on the hand's surface points (P, the vertices of `TruthSkin`): their rest
    positions and bones; `instant` (F,P) for grasp takes with an object (the skin touching it),
    `accumulated` (P,) for grasp and canonical (the paint) takes."""

    GROUP: ClassVar[str] = "contact"
    points_rest: np.ndarray
    bone: np.ndarray
    instant: np.ndarray | None = None
    accumulated: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class TruthObject:
    """The object's pose on every tick: x_world = R @ x_object + t."""

    GROUP: ClassVar[str] = "object"
    name: str
    R: np.ndarray
    t: np.ndarray


Record = TypeVar("Record", TruthInfo, TruthCameras, TruthClock, TruthFrames, TruthHand, TruthSkin, TruthContact,
                 TruthObject)


def write_record(f: h5py.File, record: Record, compressed: Collection[str] = ()) -> None:
    """Write a record into its group of an open file: arrays as datasets (gzip for the fields
    named in `compressed`), tuples of strings as string datasets, the rest as attributes."""
    group = f.require_group(record.GROUP)
    for field in dataclasses.fields(record):
        value = getattr(record, field.name)
        if value is None:
            continue
        if isinstance(value, tuple):
            group[field.name] = np.array(value, dtype=h5py.string_dtype())
        elif isinstance(value, np.ndarray):
            group.create_dataset(field.name, data=value, **(GZIP if field.name in compressed else {}))
        else:
            group.attrs[field.name] = value


class GroundTruth:
    """The reader: each record is read when first asked for, label images one by one."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise GroundTruthError(f"{self.path}: missing (only simulated takes have ground truth)")

    @classmethod
    def of_take(cls, take_dir: str | Path) -> GroundTruth:
        return cls(Path(take_dir) / FILE_NAME)

    def has(self, record: type[Record]) -> bool:
        """Whether the file has the record's group (the hand, contact and object are optional)."""
        with self._open() as f:
            return record.GROUP in f

    @cached_property
    def info(self) -> TruthInfo:
        return self._read(TruthInfo)

    @cached_property
    def cameras(self) -> TruthCameras:
        return self._read(TruthCameras)

    @cached_property
    def clock(self) -> TruthClock:
        return self._read(TruthClock)

    @cached_property
    def frames(self) -> TruthFrames:
        return self._read(TruthFrames)

    @cached_property
    def hand(self) -> TruthHand:
        return self._read(TruthHand)

    @cached_property
    def skin(self) -> TruthSkin:
        return self._read(TruthSkin)

    @cached_property
    def contact(self) -> TruthContact:
        return self._read(TruthContact)

    @cached_property
    def object(self) -> TruthObject:
        return self._read(TruthObject)

    @cached_property
    def label_frames(self) -> np.ndarray:
        """(F',) the ticks that have label images; empty when none were asked for."""
        with self._open() as f:
            return np.asarray(f[LABEL_FRAMES][()], np.int64) if LABEL_FRAMES in f else np.zeros(0, np.int64)

    @cached_property
    def label_size(self) -> tuple[int, int]:
        """(H, W) of the label images: the largest camera's image size."""
        with self._open() as f:
            return tuple(int(n) for n in self._dataset(f, LABEL_IMAGE).shape[2:])

    def tick_at(self, t_ns: np.ndarray) -> np.ndarray:
        """The nearest nominal tick (int64, not clipped) of host-clock times."""
        info = self.info
        return np.rint((np.asarray(t_ns, np.float64) - info.t0_ns) * info.fps / 1e9).astype(np.int64)

    def labels(self, rows: Sequence[int] | None = None) -> np.ndarray:
        """Label images (C,R,H,W) uint8 of every camera for rows of `label_frames` (None: all)."""
        with self._open() as f:
            image = self._dataset(f, LABEL_IMAGE)
            if rows is None:
                return image[()]
            rows = np.asarray(rows, np.int64)
            unique, back = np.unique(rows, return_inverse=True)
            if not unique.size:
                return np.zeros((image.shape[0], 0) + image.shape[2:], np.uint8)
            # h5py reads a list of distinct, increasing indices
            return image[:, unique.tolist()][:, back]

    def label_images(self, cameras: Sequence[int], rows: Sequence[int]) -> np.ndarray:
        """Label images (N,H,W) uint8 of the pairs (cameras[i], rows[i]) (camera: its position
        in `cameras.ids`, row: its position in `label_frames`), reading only those."""
        with self._open() as f:
            image = self._dataset(f, LABEL_IMAGE)
            out = np.zeros((len(cameras),) + image.shape[2:], np.uint8)
            for i, (c, r) in enumerate(zip(cameras, rows)):
                out[i] = image[int(c), int(r)]
        return out

    def _open(self) -> h5py.File:
        try:
            return h5py.File(self.path, "r")
        except OSError as exc:
            raise GroundTruthError(f"{self.path}: cannot be read as HDF5 ({exc})") from None

    def _dataset(self, f: h5py.File, key: str) -> h5py.Dataset:
        if not isinstance(f.get(key), h5py.Dataset):
            raise GroundTruthError(f"{self.path}: missing {key}")
        return f[key]

    def _read(self, record: type[Record]) -> Record:
        values = {}
        with self._open() as f:
            if record.GROUP not in f:
                raise GroundTruthError(f"{self.path}: no {record.GROUP} group (not the truth of a take with one)")
            group = f[record.GROUP]
            for field in dataclasses.fields(record):
                node = group.get(field.name)
                if isinstance(node, h5py.Dataset):
                    value = node[()]
                    values[field.name] = tuple(v.decode() if isinstance(v, bytes) else str(v) for v in value) \
                        if value.dtype.kind in "OS" else value
                elif field.name in group.attrs:
                    value = group.attrs[field.name]
                    values[field.name] = value.item() if isinstance(value, np.generic) else value
                elif field.default is dataclasses.MISSING:
                    key = field.name if record.GROUP == "/" else f"{record.GROUP}/{field.name}"
                    raise GroundTruthError(f"{self.path}: missing {key}")
        return record(**values)
