"""A MANUS / BRICS release made into a session of this toolkit (docs/datasets.md).

One take per capture: frames.csv from each camera's timestamp file, take.json naming the release's
video where it lies (take.json "videos", so nothing is copied), cameras.json from optim_params.txt,
and the release's keypoints, joint angles and masks in the session's DATASET.h5. A video is
re-muxed into cams/CAM.mkv (its packets copied, never re-encoded) only where frames must be left
out (frames without a timestamp, timestamps that go back) or where --copy asks for a take that does
not depend on the release staying where it is.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from dataset_tools.calibration.formats.manus_optim_params import read_manus
from manus_core.cameras import CameraRig
from manus_core.errors import ReleaseError
from manus_core.fileio import atomic_output, write_atomic
from manus_core.frames_csv import FILE_NAME as FRAMES_CSV
from manus_core.frames_csv import HEADER, format_row
from manus_core.progress import Progress, silent
from manus_core.session import check_take_name
from manus_core.take import video_packets
from rig.mkv import MkvWriter

from .brics_files import KIND_FOLDERS, camera_videos, find_captures, find_optim_params, read_timestamps, timestamp_file
from .brics_poses import import_poses

MJPEG_FOURCCS = {"MJPG", "AVI1", "JPEG"}
KINDS = {"grasp": "grasp", "calib": "calibration", "object": "object", "canonical": "canonical"}
REMUX_BATCH = 64


@dataclass(frozen=True)
class CameraImport:
    """One camera of an imported take: frames kept, where its video is, and what was left out."""

    id: str
    frames: int
    video: str                # referenced | re-muxed | copied
    problems: tuple[str, ...]


@dataclass(frozen=True)
class TakeImport:
    name: str
    path: Path
    kind: str
    cameras: tuple[CameraImport, ...]
    left_out: tuple[str, ...]     # cameras of the release that are not in the take, with why
    poses: tuple[str, ...]        # what went into DATASET.h5


@dataclass(frozen=True)
class ImportSummary:
    session: Path
    calibration: Path
    dataset: Path | None
    takes: tuple[TakeImport, ...]


def take_name(capture: Path) -> str:
    """The capture's name without the release's DATE_session_ prefix, made a valid take name."""
    name = re.sub(r"^.*?_session_", "", capture.name) or capture.name
    return check_take_name(re.sub(r"[^A-Za-z0-9._-]", "-", name))


def take_kind(capture: Path) -> str:
    """The kind of take a capture is: by the folder it is filed under (grasps/, objects/, ...), else
    by a word in its name, else hand."""
    by_folder = {folder: kind for kind, folder in KIND_FOLDERS.items()}
    if capture.parent.name in by_folder:
        return by_folder[capture.parent.name]
    return next((kind for word, kind in KINDS.items() if word in capture.name.lower()), "hand")


def video_info(path: Path) -> tuple[int, int]:
    """(width, height) of a release's video; ReleaseError unless it is MJPEG (its packets are JPEGs)."""
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise ReleaseError(f"{path}: cannot be opened as a video")
        fourcc = int(cap.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little").decode("ascii", "replace")
        if fourcc.upper() not in MJPEG_FOURCCS:
            raise ReleaseError(f"{path}: codec {fourcc!r}: this toolkit reads MJPEG videos (its frames stay "
                               "the camera's JPEGs); re-encode it first, e.g. ffmpeg -i IN -c:v mjpeg -q:v 2 OUT.avi")
        return int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    finally:
        cap.release()


def kept_frames(t_us: np.ndarray, frames: int) -> tuple[np.ndarray, list[str]]:
    """Which of a video's frames have a timestamp that moves forward (bool (frames,)), and what was
    wrong: frames past the last timestamp line, timestamp lines past the last frame, timestamps
    that are not later than an earlier one."""
    n = min(len(t_us), frames)
    keep = np.zeros(frames, bool)
    keep[:n] = True
    if n > 1:
        keep[1:n] = t_us[1:n] > np.maximum.accumulate(t_us[:n])[:-1]
    problems = []
    if frames > len(t_us):
        problems.append(f"{frames - len(t_us)} frames after the last timestamp line dropped")
    if len(t_us) > frames:
        problems.append(f"{len(t_us) - frames} timestamp lines have no frame in the video")
    back = int(n - keep[:n].sum())
    if back:
        problems.append(f"{back} frames whose timestamp is not later than an earlier one dropped")
    return keep, problems


def _remux(src: Path, keep: np.ndarray, dst: Path, size: tuple[int, int], fps: float) -> None:
    """The kept packets of `src` into an MJPEG Matroska file, bytes unchanged, atomically."""
    with atomic_output(dst) as tmp, MkvWriter(tmp, size[0], size[1], fps, fsync=False) as mkv:
        batch: list[bytes] = []
        for k, packet in enumerate(video_packets(src)):
            if k < len(keep) and keep[k]:
                batch.append(packet.tobytes())
            if len(batch) == REMUX_BATCH:
                mkv.write(batch)
                batch = []
        if batch:
            mkv.write(batch)


def _target(session: Path, name: str, force: bool) -> Path:
    take = session / name
    if take.exists():
        try:
            imported = "imported" in json.loads((take / "take.json").read_text())
        except (OSError, ValueError, TypeError):   # no take.json, or not one: not ours to replace
            imported = False
        if not force or not imported:
            raise ReleaseError(f"{take}: exists" + (" (use --force to import it again)" if imported else
                                                   " and is not an imported take; import into another session"))
        shutil.rmtree(take)
    return take


def import_capture(capture: Path, session: Path, rig: CameraRig, *, annotations: Path | None = None,
                   units: str | None = None, copy: bool = False, strict: bool = False, kind: str | None = None,
                   calibration: Path | None = None, force: bool = False,
                   progress: Progress = silent) -> TakeImport:
    """One capture folder (CAPTURE/synced/...) as the take SESSION/NAME, plus its poses in DATASET.h5."""
    name = take_name(capture)
    videos = camera_videos(capture)
    left_out = [f"{cam}: in the cameras file, no video in {capture / 'synced'}" for cam in rig.ids if cam not in videos]
    left_out += [f"{cam}: a video, not in the cameras file" for cam in videos if cam not in rig.ids]
    stamps = {cam: timestamp_file(v) for cam, v in videos.items() if cam in rig.ids}
    left_out += [f"{cam}: no {cam}_synced_files.txt beside {videos[cam].name}"
                 for cam, s in stamps.items() if s is None]
    if left_out and strict:
        raise ReleaseError(f"{capture}: " + "; ".join(left_out))
    cams = [c for c in rig.ids if c in stamps and stamps[c] is not None]
    if not cams:
        raise ReleaseError(f"{capture}: no camera has both a video, a timestamp file and an entry in the cameras file")
    take = _target(session, name, force)
    t_us = {cam: read_timestamps(stamps[cam]) for cam in cams}
    # the span over the frame count: one host-side jitter per camera, not one per frame
    periods = [(t[-1] - t[0]) / (len(t) - 1) for t in t_us.values() if len(t) > 1 and t[-1] > t[0]]
    fps = round(1e6 / float(np.median(periods)), 3) if periods else 30.0
    rows: list[tuple[int, str]] = []
    entries, named, found = [], {}, []
    take.mkdir(parents=True)
    try:
        for i, cam in enumerate(cams):
            video = videos[cam]
            size = video_info(video)
            sizes = np.array([p.size for p in video_packets(video)], np.int64)
            keep, problems = kept_frames(t_us[cam], len(sizes))
            if strict and problems:
                raise ReleaseError(f"{stamps[cam]}: " + "; ".join(problems))
            if keep.all() and not copy:
                named[cam] = os.path.relpath(video, take)
                how = "referenced"
            else:
                _remux(video, keep, take / "cams" / f"{cam}.mkv", size, fps)
                how = "copied" if keep.all() else "re-muxed"
            index = np.flatnonzero(keep)
            ns = t_us[cam][index] * 1000
            rows += [(int(t), format_row(cam, int(k), int(t), int(t), int(sizes[k]), 0)) for k, t in zip(index, ns)]
            entries.append({"id": cam, "width": size[0], "height": size[1], "fps": fps, "encoding": "jpeg",
                            "pixel_format": "MJPG", "frames": int(len(index)), "status": "ok",
                            "source": str(video.resolve()), "timestamps": str(stamps[cam].resolve()),
                            "dropped": problems})
            found.append(CameraImport(cam, int(len(index)), how, tuple(problems)))
            progress(f"import {name}", i + 1, len(cams))
        rows.sort(key=lambda r: r[0])
        write_atomic(take / FRAMES_CSV, (HEADER + "\n" + "".join(r for _, r in rows)).encode())
        starts = [int(t_us[c][0]) * 1000 for c in cams if len(t_us[c])]
        meta = {"version": 1, "take": name, "kind": kind or take_kind(capture), "rig": "imported",
                "cameras": entries, "fps": fps, "resolution": [entries[0]["width"], entries[0]["height"]],
                "sync": "free-run",
                "t0_ns": min(starts) if starts else 0, "status": "complete", "reason": "",
                "videos": named, "imported": {"from": "MANUS/BRICS release", "capture": str(capture.resolve()),
                                              "left_out": left_out}}
        write_atomic(take / "take.json", json.dumps(meta, indent=1).encode())
    except BaseException:
        shutil.rmtree(take, ignore_errors=True)
        raise
    poses = import_poses(take, capture, rig, cams, annotations=annotations, units=units, calibration=calibration)
    return TakeImport(name, take, meta["kind"], tuple(found), tuple(left_out), tuple(poses))


def import_release(src: str | Path, session: str | Path, *, cameras: str | Path | None = None,
                   annotations: str | Path | None = None, units: str | None = None, copy: bool = False,
                   strict: bool = False, kind: str | None = None, force: bool = False,
                   progress: Progress = silent) -> ImportSummary:
    """Every capture of a release folder into SESSION: the calibration as SESSION/calibration/
    cameras.json, one take per capture, their poses and masks in SESSION/DATASET.h5."""
    src, session = Path(src), Path(session)
    captures = find_captures(src)
    params = Path(cameras) if cameras is not None else find_optim_params(src, captures[0])
    rig = read_manus(params, units)
    calibration = session / "calibration" / "cameras.json"
    session.mkdir(parents=True, exist_ok=True)
    rig.save(calibration)
    takes = [import_capture(c, session, rig, annotations=None if annotations is None else Path(annotations),
                            units=units, copy=copy, strict=strict, kind=kind, calibration=calibration, force=force,
                            progress=progress) for c in captures]
    dataset = session / "DATASET.h5"
    return ImportSummary(session, calibration, dataset if dataset.exists() else None, tuple(takes))
