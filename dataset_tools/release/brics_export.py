"""Takes of this toolkit written in the MANUS / BRICS release layout, so that MANUS's own code (and
whatever reads its releases) trains on our captures (docs/datasets.md, "Export").

    OUT/optim_params.txt
    OUT/WHICH/DATE_session_TAKE/synced/CAM/CAM.avi (+ CAM_synced_files.txt)   packets copied as they are
    OUT/WHICH/DATE_session_TAKE/pose_dumps/{keypoints_2d/CAM,keypoints_3d,joint_angles,joint_angles_filtered}/
    OUT/WHICH/DATE_session_TAKE/pose_dumps/bone_lens.json
    OUT/WHICH/DATE_session_TAKE/images/refined_seg/CAM/NNNNNNNN.png    BGRA, alpha = hand (object take: object)
    OUT/WHICH/DATE_session_TAKE/images/refined_seg_object/CAM/...      a grasp's object masks (ours)
    OUT/actions_hdf5/TAKE.hdf5          K, extr (3x4), frames/N/images/CAM (RGBA crops), frames/N/bbox/CAM

WHICH is grasps, actions (hand takes), objects, calibration or canonical, by the take's kind, as
MANUS files its captures. A release's synced videos are index-aligned: frame n of every camera is
one moment. So the frame groups in which every exported camera has a frame are written, in order,
as frames 0, 1, ...; the others are left out and counted. Keypoints go out in undistorted pixels of the same K, and the
HDF5 crops are undistorted the same way, as MANUS reads both without undistorting them again.
The export is built in a folder beside OUT and renamed into place when complete.
"""

from __future__ import annotations

import datetime
import json
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import cv2
import h5py
import numpy as np

from dataset_tools.calibration.formats import load_cameras
from dataset_tools.calibration.formats.manus_optim_params import write_manus
from dataset_tools.sync import frame_groups
from dataset_tools.undistort import undistort_points
from manus_core.cameras import CameraRig
from manus_core.dataset import read_dataset, take_key
from manus_core.errors import ReleaseError
from manus_core.progress import Progress, silent
from manus_core.take import Take
from rig.mkv import MkvWriter

from .brics_angles import to_release
from .brics_files import (
    KIND_FOLDERS,
    MASKS,
    OBJECT_MASKS,
    OPTIM_PARAMS,
    POSE_DUMPS,
    SYNCED,
    frame_name,
    write_timestamps,
)

CROP_MARGIN = 0.15     # of the mask's box, on every side


@dataclass(frozen=True)
class TakeExport:
    take: Path
    capture: Path
    frames: int               # frame groups written (every camera has a frame in each)
    left_out_groups: int      # groups without a frame of some camera
    parts: tuple[str, ...]


def _undistorted_pixels(rig: CameraRig, pixels: np.ndarray) -> np.ndarray:
    """Raw pixels (C,N,2) to undistorted pixels of the same K (C,N,2)."""
    xy = undistort_points(rig, pixels)
    K = rig.K
    return np.stack([K[:, 0, 0, None] * xy[..., 0] + K[:, 0, 1, None] * xy[..., 1] + K[:, 0, 2, None],
                     K[:, 1, 1, None] * xy[..., 1] + K[:, 1, 2, None]], -1)


def _write_video(take: Take, cam: str, frames: np.ndarray, path: Path, fps: float, size: np.ndarray) -> None:
    """Frames `frames` (increasing) of a camera as an MJPEG AVI, packets unchanged (ffmpeg remuxes)."""
    if shutil.which("ffmpeg") is None:
        raise ReleaseError("ffmpeg not found: the export writes AVI with `ffmpeg -c copy` (apt-get install ffmpeg)")
    wanted = set(int(k) for k in frames)
    w, h = (int(v) for v in size)
    mkv = path.with_suffix(".mkv")
    with MkvWriter(mkv, w, h, fps, fsync=False) as out:
        for k, packet in enumerate(take.packets(cam)):
            if k in wanted:
                out.write(packet.tobytes())
            if k >= frames[-1]:
                break
    done = subprocess.run(["ffmpeg", "-v", "error", "-y", "-i", str(mkv), "-c", "copy", "-f", "avi", str(path)],
                          capture_output=True, text=True)
    mkv.unlink()
    if done.returncode != 0:
        raise ReleaseError(f"{path}: ffmpeg could not remux {take.video_path(cam)}: {done.stderr.strip()}")


def _poses(ann, rows: np.ndarray, cams: list[str], rig: CameraRig, folder: Path) -> list[str]:
    """pose_dumps/ of the annotation rows `rows` (exported as frames 0, 1, ...)."""
    order = [ann.cameras.index(c) for c in cams]
    kp = ann.keypoints2d[rows][:, order].astype(np.float64)               # (N,C,21,3)
    und = _undistorted_pixels(rig, kp[..., :2].transpose(1, 0, 2, 3).reshape(len(cams), -1, 2))
    kp[..., :2] = und.reshape(len(cams), len(rows), 21, 2).transpose(1, 0, 2, 3)
    seen = (kp[..., 2] > 0) & np.isfinite(kp[..., :2]).all(-1)
    kp[~seen] = 0.0
    translation, eulers = to_release(ann.joint_angles_raw[rows])
    f_translation, f_eulers = to_release(ann.joint_angles[rows])
    X = ann.keypoints3d[rows]
    valid = np.isfinite(X).all(-1)
    X4 = np.concatenate([np.where(valid[..., None], X, 0.0), valid[..., None].astype(float)], -1)
    for n in range(len(rows)):
        name = frame_name(n)
        for c, cam in enumerate(cams):
            if seen[n, c].any():
                _write(folder / "keypoints_2d" / cam / name, kp[n, c].tolist())
        if valid[n].any():
            _write(folder / "keypoints_3d" / name, X4[n].tolist())
        # JSON has no NaN: a frame whose fit left any angle undetermined has no pose file
        if np.isfinite(eulers[n]).all() and np.isfinite(translation[n]).all():
            _write(folder / "joint_angles" / name,
                   {"translation": translation[n].tolist(), "angles": eulers[n].tolist()})
        if np.isfinite(f_eulers[n]).all() and np.isfinite(f_translation[n]).all():
            _write(folder / "joint_angles_filtered" / name,
                   {"translation": f_translation[n].tolist(), "angles": f_eulers[n].tolist()})
    _write(folder / "bone_lens.json", ann.bone_lengths.tolist())
    return ["keypoints_2d", "keypoints_3d", "joint_angles", "bone_lens.json"]


def _write(path: Path, doc) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc))


def dataset_masks(dataset: Path, key: str, frame_ns: np.ndarray, cams: list[str]) -> dict[str, np.ndarray] | None:
    """{"hand", "object"}: (N,C,H,W) masks that segment stored for the frame groups frame_ns of take
    `key`, and "present" (N,) where it stored any; None when the take has no masks of every camera."""
    ds = read_dataset(dataset)
    if key not in ds or "segment" not in ds.stages(key):
        return None
    with h5py.File(dataset, "r") as f:
        group = f[key]
        mask_cams = [c.decode() if isinstance(c, bytes) else str(c) for c in group.attrs["mask_cameras"]]
        if any(c not in mask_cams for c in cams):
            return None
        lookup = {int(t): i for i, t in enumerate(group["masks/frame_ns"][()])}
        rows = [lookup.get(int(t), -1) for t in frame_ns]
        order = [mask_cams.index(c) for c in cams]
        out = {}
        for part in ("hand", "object"):
            masks = group[f"masks/{part}"]
            shape = (len(frame_ns), len(cams)) + masks.shape[2:]
            out[part] = np.zeros(shape, bool)
            for n, r in enumerate(rows):
                if r >= 0:
                    out[part][n] = masks[r][order]
        out["present"] = np.array([r >= 0 for r in rows])
    return out


def _mask_images(take: Take, masks: dict, frames: np.ndarray, cams: list[str], images: list[dict],
                 capture: Path) -> None:
    object_take = take.meta.get("kind") == "object"
    parts = [("object", MASKS)] if object_take else [("hand", MASKS), ("object", OBJECT_MASKS)]
    for n in np.flatnonzero(masks["present"]):
        for c, cam in enumerate(cams):
            image = images[c][int(frames[n, c])]
            for part, folder in parts:
                if part == "object" and not object_take and not masks["object"][n, c].any():
                    continue
                bgra = np.dstack([image, masks[part][n, c].astype(np.uint8) * 255])
                path = capture / folder / cam / frame_name(int(n), ".png")
                path.parent.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(path), bgra)


def _hand_hdf5(rig: CameraRig, masks: dict, frames: np.ndarray, cams: list[str], images: list[dict],
               path: Path) -> int:
    """actions_hdf5/TAKE.hdf5: per camera K and extr (3x4), per masked frame the hand's undistorted
    RGBA crop and its box [xmin, ymin, xmax, ymax] (exclusive max). Returns the frames written.
    images: per camera {frame index: image} of the masked frames."""
    path.parent.mkdir(parents=True, exist_ok=True)
    written = 0
    with h5py.File(path, "w") as f:
        for c, cam in enumerate(cams):
            f[f"K/{cam}"] = rig.K[c]
            f[f"extr/{cam}"] = np.hstack([rig.R[c], rig.t[c][:, None]])
        maps = [cv2.initUndistortRectifyMap(rig.K[c], rig.dist[c], None, rig.K[c],
                                            tuple(int(v) for v in rig.size[c]), cv2.CV_32FC1) for c in range(len(cams))]
        for n in np.flatnonzero(masks["present"]):
            for c, cam in enumerate(cams):
                image = cv2.remap(images[c][int(frames[n, c])], *maps[c], cv2.INTER_LINEAR)
                mask = cv2.remap(masks["hand"][n, c].astype(np.uint8) * 255, *maps[c], cv2.INTER_NEAREST)
                ys, xs = np.nonzero(mask)
                if not len(xs):
                    continue
                mx = int(np.ceil((xs.max() - xs.min() + 1) * CROP_MARGIN))
                my = int(np.ceil((ys.max() - ys.min() + 1) * CROP_MARGIN))
                x0, y0 = max(0, xs.min() - mx), max(0, ys.min() - my)
                x1, y1 = min(mask.shape[1], xs.max() + 1 + mx), min(mask.shape[0], ys.max() + 1 + my)
                rgba = np.dstack([image[y0:y1, x0:x1, ::-1], mask[y0:y1, x0:x1]])
                f[f"frames/{n}/images/{cam}"] = rgba
                f[f"frames/{n}/bbox/{cam}"] = np.array([x0, y0, x1, y1], np.int64)
            written += 1
    return written


def export_take(take_path: Path, rig: CameraRig, out: Path, dataset: Path | None,
                progress: Progress = silent) -> TakeExport:
    take = Take(take_path)
    key = take_key(take.path)
    ann = None
    if dataset is not None and dataset.exists():
        ds = read_dataset(dataset)
        ann = ds[key] if key in ds and "annotate" in ds.stages(key) else None
    cams = [c for c in rig.ids if c in take.cameras and (ann is None or c in ann.cameras)]
    if len(cams) < 2:
        raise ReleaseError(f"{take.path}: fewer than 2 of its cameras are calibrated; nothing to export")
    if ann is not None:
        frame_ns, index = ann.frame_ns, ann.frame_index[:, [ann.cameras.index(c) for c in cams]]
    else:
        groups = frame_groups(take)
        frame_ns, index = groups.frame_ns, groups.frame_index[:, [groups.cameras.index(c) for c in cams]]
    complete = np.flatnonzero((index >= 0).all(1))
    if not len(complete):
        raise ReleaseError(f"{take.path}: no frame group has a frame of every exported camera")
    frames = index[complete]
    created = str(take.meta.get("created", ""))[:10] or datetime.date.today().isoformat()
    capture = out / KIND_FOLDERS.get(str(take.meta.get("kind")), "actions") / f"{created}_session_{take.path.name}"
    fps = take.fps or 30.0
    sub = rig.subset(cams)
    for c, cam in enumerate(cams):
        folder = capture / SYNCED / cam
        folder.mkdir(parents=True, exist_ok=True)
        _write_video(take, cam, frames[:, c], folder / f"{cam}.avi", fps, sub.size[c])
        t_us = take.camera_frames(cam)["t_host_ns"][frames[:, c]] // 1000
        write_timestamps(folder / f"{cam}_synced_files.txt", t_us)
        progress(f"export {take.path.name}", c + 1, len(cams))
    parts = ["synced"]
    if ann is not None:
        parts += _poses(ann, complete, cams, sub, capture / POSE_DUMPS)
    masks = dataset_masks(dataset, key, frame_ns[complete], cams) if dataset is not None and dataset.exists() else None
    if masks is not None and masks["present"].any():
        # each camera's masked frames, decoded in one pass over its video for both outputs
        images = [take.read_frames(cam, frames[masks["present"], c]) for c, cam in enumerate(cams)]
        _mask_images(take, masks, frames, cams, images, capture)
        parts.append("masks")
        if take.meta.get("kind") in ("hand", "grasp") and _hand_hdf5(
                sub, masks, frames, cams, images, out / "actions_hdf5" / f"{take.path.name}.hdf5"):
            parts.append("actions_hdf5")
    return TakeExport(take.path, capture, len(complete), int(len(index) - len(complete)), tuple(parts))


def export_release(takes: list[str | Path], calib: str | Path, out: str | Path, *, dataset: str | Path | None = None,
                   force: bool = False, progress: Progress = silent) -> list[TakeExport]:
    """Takes (and their annotations and masks in `dataset`) as a release folder OUT."""
    out = Path(out)
    if out.exists() and any(out.iterdir()) and not force:
        raise ReleaseError(f"{out}: exists and is not empty (use --force to replace it)")
    calib = Path(calib)
    rig = load_cameras(calib)
    staging = out.parent / f".{out.name}.partial"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    try:
        write_manus(rig, staging / OPTIM_PARAMS, lossy=False)
        found = [export_take(Path(t), rig, staging, None if dataset is None else Path(dataset), progress)
                 for t in takes]
        if out.exists():
            shutil.rmtree(out)
        staging.rename(out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return [TakeExport(e.take, out / e.capture.relative_to(staging), e.frames, e.left_out_groups, e.parts)
            for e in found]
