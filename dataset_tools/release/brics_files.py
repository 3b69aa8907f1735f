"""The files of a MANUS / BRICS release (MANUS-Grasps, DiVa360 and the sessions GigaHands shares
its layout with), read and written field by field as docs/datasets.md describes them.

    CAPTURE/synced/CAM/CAM.avi                  MJPEG, frames index-aligned across cameras
    CAPTURE/synced/CAM/CAM_synced_files.txt     one line per frame; field 3 = timestamp in us
                   (CAM_syncedaudio_files.txt is preferred where both are there)
    optim_params.txt                            the cameras (calibration.formats.manus_optim_params)
    CAPTURE/pose_dumps/keypoints_2d/CAM/NNNNNNNN.json   21 x [x, y, conf], undistorted pixels
    CAPTURE/pose_dumps/keypoints_3d/NNNNNNNN.json       21 x [X, Y, Z, valid]
    CAPTURE/pose_dumps/joint_angles[_filtered]/NNNNNNNN.json  {"translation": [3], "angles": 21 x 3}
    CAPTURE/pose_dumps/bone_lens.json                   20 bone lengths
    CAPTURE/images/refined_seg/CAM/NNNNNNNN.png         BGRA, alpha = mask

NNNNNNNN is the frame's index in the synced videos, eight digits. Folders named imu or mic under
synced/ are not cameras. Pickle files of a release are never opened.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np

from manus_core.errors import ReleaseError
from manus_core.fileio import write_atomic

SYNCED = "synced"
POSE_DUMPS = "pose_dumps"
OPTIM_PARAMS = "optim_params.txt"
NOT_CAMERAS = ("imu", "mic")
MASKS = Path("images") / "refined_seg"
OBJECT_MASKS = Path("images") / "refined_seg_object"   # ours: the object of a grasp, beside the hand
TIMESTAMP_SUFFIXES = ("_syncedaudio_files.txt", "_synced_files.txt")
_FRAME_NAME = re.compile(r"^(\d+)$")
# the folder a release files a capture under, by the kind of take it is
KIND_FOLDERS = {"grasp": "grasps", "hand": "actions", "object": "objects", "calibration": "calibration",
                "canonical": "canonical"}


def frame_name(k: int, suffix: str = ".json") -> str:
    return f"{k:08d}{suffix}"


def find_captures(src: Path) -> list[Path]:
    """The captures of a release folder: SRC itself when it holds synced/, else the sub-folders (or
    their sub-folders) that do."""
    src = Path(src)
    if not src.is_dir():
        raise ReleaseError(f"{src}: no such folder")
    if (src / SYNCED).is_dir():
        return [src]
    # SRC/CAPTURE/synced, or SRC/WHICH/CAPTURE/synced as MANUS files captures under grasps/, actions/, ...
    found = sorted(p.parent for p in src.glob(f"*/{SYNCED}") if p.is_dir()) or sorted(
        p.parent for p in src.glob(f"*/*/{SYNCED}") if p.is_dir())
    if not found:
        raise ReleaseError(f"{src}: not a MANUS/BRICS release: no {SYNCED}/ folder in it or in its sub-folders "
                           f"(looked for {SYNCED}/CAM/CAM.avi)")
    return found


def find_optim_params(src: Path, capture: Path) -> Path:
    """The cameras file: in the capture, in the release folder, or in a calib* folder beside (MANUS
    keeps calib.object/optim_params.txt per subject)."""
    src = Path(src)
    places = [capture / OPTIM_PARAMS, src / OPTIM_PARAMS, *sorted(src.glob(f"calib*/{OPTIM_PARAMS}")),
              *sorted(src.parent.glob(f"calib*/{OPTIM_PARAMS}"))]
    for place in places:
        if place.is_file():
            return place
    raise ReleaseError(f"{src}: no {OPTIM_PARAMS} (looked in {capture}, {src}, {src}/calib*/ and "
                       f"{src.parent}/calib*/); name it with --cameras")


def camera_videos(capture: Path) -> dict[str, Path]:
    """CAM -> synced/CAM/CAM.avi (or the folder's one .avi), sorted by name; imu and mic are left out."""
    out = {}
    for folder in sorted((capture / SYNCED).iterdir()):
        if not folder.is_dir() or any(n in folder.name for n in NOT_CAMERAS):
            continue
        named = folder / f"{folder.name}.avi"
        videos = [named] if named.is_file() else sorted(folder.glob("*.avi"))
        if videos:
            out[folder.name] = videos[0]
    return out


def timestamp_file(video: Path) -> Path | None:
    cam = video.parent.name
    return next((video.parent / f"{cam}{s}" for s in TIMESTAMP_SUFFIXES if (video.parent / f"{cam}{s}").is_file()),
                None)


def read_timestamps(path: Path) -> np.ndarray:
    """Each line's third field, microseconds (int64), one per frame of the video beside it."""
    out = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        fields = line.split()
        if not fields:
            continue
        try:
            out.append(int(fields[2]))
        except (IndexError, ValueError):
            raise ReleaseError(f"{path}:{number}: expected a timestamp in microseconds as the third field, "
                               f"got {line.strip()!r}") from None
    return np.asarray(out, np.int64)


def write_timestamps(path: Path, t_us: np.ndarray) -> None:
    """One line per frame: 'INDEX INDEX TIMESTAMP_US'. The release's first two fields are read by no
    public code; ours repeat the frame index there."""
    text = "".join(f"{k} {k} {int(t)}\n" for k, t in enumerate(t_us))
    write_atomic(path, text.encode())


def read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ReleaseError(f"{path}: not readable JSON ({exc})") from None


def write_json(path: Path, doc: Any) -> None:
    write_atomic(path, json.dumps(doc).encode())


def frame_files(folder: Path, suffix: str = ".json") -> dict[int, Path]:
    """Frame index -> file of a folder of NNNNNNNN.json (or .png) files; other names are ignored."""
    if not folder.is_dir():
        return {}
    out = {}
    for path in folder.iterdir():
        match = _FRAME_NAME.match(path.stem)
        if match and path.suffix == suffix:
            out[int(match.group(1))] = path
    return dict(sorted(out.items()))


def read_points(path: Path, width: int) -> np.ndarray:
    """A (21, width) float array from a JSON list of 21 points of `width` numbers."""
    doc = read_json(path)
    try:
        points = np.asarray(doc, np.float64)
    except (TypeError, ValueError):
        points = np.empty(0)
    if points.shape != (21, width):
        raise ReleaseError(f"{path}: expected 21 points of {width} numbers, got {np.shape(doc)}")
    return points


def read_pose(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(translation (3,), angles (21,3)) of a joint_angles file."""
    doc = read_json(path)
    try:
        translation = np.asarray(doc["translation"], np.float64)
        angles = np.asarray(doc["angles"], np.float64)
    except (KeyError, TypeError, ValueError):
        raise ReleaseError(f"{path}: expected {{'translation': [3], 'angles': 21 x 3}}") from None
    if translation.shape != (3,) or angles.shape != (21, 3):
        raise ReleaseError(f"{path}: translation {translation.shape} and angles {angles.shape}, expected (3,) and "
                           "(21, 3)")
    return translation, angles


def read_bone_lengths(path: Path) -> np.ndarray:
    doc = read_json(path)
    try:
        lengths = np.asarray(doc, np.float64)
    except (TypeError, ValueError):
        lengths = np.empty(0)
    if lengths.shape != (20,) or not np.all(lengths > 0):
        raise ReleaseError(f"{path}: expected 20 positive bone lengths")
    return lengths
