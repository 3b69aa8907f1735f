"""One frame group of a take as a dataset nerfstudio's and gsplat's trainers read as it is.

    OUT/images/CAM.png    the group's frame of each camera, raw (distorted), as recorded
    OUT/masks/CAM.png     its foreground mask, 255 = foreground (only when masks are given)
    OUT/transforms.json   nerfstudio's format, intrinsics and distortion per frame
    OUT/sparse/0/         the same cameras as a COLMAP text model, images named CAM.png

Relied on: nerfstudio's "Data conventions" page and its nerfstudio_dataparser / cameras modules.

Conventions, from those:
- transform_matrix is camera-to-world with OpenGL/Blender camera axes (x right, y up, z back):
  OpenCV's camera-to-world with its y and z columns negated.
- nerfstudio casts the ray of pixel (row i, column j) through (j + 0.5, i + 0.5) measured against
  cx, cy: its principal point is OpenCV's plus half a pixel, as COLMAP's is, so transforms.json
  and sparse/0 hold the same numbers.
- nerfstudio knows no "FULL_OPENCV" camera model, but its "OPENCV" reads k1 k2 k3 k4 p1 p2 from
  each frame: every frame gets k3 (and camera_model is always "OPENCV"). COLMAP's OPENCV has no
  k3, so a camera with k3 != 0 is FULL_OPENCV in sparse/0 (dataset_tools.calibration.formats
  .colmap_text decides that), which gsplat's COLMAP parser does not read.
- nerfstudio wants a mask_path on every frame or on none: given masks, every camera written needs one.

transforms.json is removed first (force) and written last, each file atomically: a transforms.json
on disk always describes a finished export.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np

from dataset_tools.calibration.formats.checks import plain_ids, require_representable
from dataset_tools.calibration.formats.colmap_text import write_colmap
from dataset_tools.sync import frame_groups
from manus_core.cameras import CameraRig
from manus_core.errors import InputError, OutputExists
from manus_core.fileio import write_atomic
from manus_core.progress import Progress, silent
from manus_core.take import Take

TRANSFORMS = "transforms.json"
SPARSE = Path("sparse") / "0"

# OpenCV camera axes (x right, y down, z forward) to nerfstudio's (x right, y up, z back)
_OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0])


def nerfstudio_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """transform_matrix (4,4) of a camera whose world-to-camera pose is x_cam = R @ X + t."""
    c2w = np.eye(4)
    c2w[:3, :3] = R.T @ _OPENCV_TO_OPENGL
    c2w[:3, 3] = -R.T @ t
    return c2w


def frame_entry(rig: CameraRig, i: int) -> dict:
    """Camera i of the rig as a frame of transforms.json, without its file paths."""
    K, (k1, k2, p1, p2, k3) = rig.K[i], rig.dist[i]
    return {"transform_matrix": nerfstudio_pose(rig.R[i], rig.t[i]).tolist(),
            "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]),
            "cx": float(K[0, 2]) + 0.5, "cy": float(K[1, 2]) + 0.5,  # pixel grid: see the module doc
            "w": int(rig.size[i, 0]), "h": int(rig.size[i, 1]),
            "k1": float(k1), "k2": float(k2), "k3": float(k3), "p1": float(p1), "p2": float(p2)}


def write_frame_group(take: Take, rig: CameraRig, group: int, out: Path, *,
                      masks: Mapping[str, np.ndarray] | None = None, force: bool = False,
                      progress: Progress = silent) -> Path:
    """Write frame group `group` of `take` to `out` (layout in the module doc); returns
    out/transforms.json.

    The cameras written are those of the take (in take.json's order) that `rig` calibrates and
    that have a frame in the group; transforms.json's "manus_capture" entry names the take, the
    group and the cameras left out for want of a frame. masks: camera -> (H,W) bool. Refuses
    (OutputExists) a non-empty `out` unless `force`, which writes over the files of the same names.
    progress("export", cameras done, cameras) after each camera.
    """
    out = Path(out)
    groups = frame_groups(take)
    count = len(groups.frame_ns)
    if not 0 <= group < count:
        raise InputError(f"{take.path}: no frame group {group}: the take has {count} frame groups"
                         + (f" (0 to {count - 1})" if count else ""))
    members, missing = _members(take, rig, groups.cameras, groups.frame_index[group], group)
    sub = rig.subset([cam for cam, _ in members])
    _check_rig(sub, out)
    if masks is not None:
        _check_masks(sub, masks, out)
    _refuse_existing(out, force)

    (out / TRANSFORMS).unlink(missing_ok=True)  # until the new one is written, no export is whole
    frames = []
    for i, (cam, k) in enumerate(members):
        image = take.read_frame(cam, k)
        width, height = (int(v) for v in sub.size[i])
        if image.shape[:2] != (height, width):
            raise InputError(f"{take.path}: camera {cam!r} frame {k} is {image.shape[1]}x{image.shape[0]} but "
                             f"its calibration is for {width}x{height}")
        frame = {"file_path": f"images/{cam}.png", **frame_entry(sub, i)}
        _write_png(out / frame["file_path"], image)
        if masks is not None:
            frame["mask_path"] = f"masks/{cam}.png"
            _write_png(out / frame["mask_path"], np.where(masks[cam], 255, 0).astype(np.uint8))
        frames.append(frame)
        progress("export", i + 1, len(members))

    write_colmap(sub, out / SPARSE, lossy=False, image_suffix=".png")
    doc = {"camera_model": "OPENCV", "frames": frames,
           "manus_capture": {"take": str(take.path), "group": int(group), "frame_ns": int(groups.frame_ns[group]),
                             "cameras_without_frame": missing}}
    write_atomic(out / TRANSFORMS, (json.dumps(doc, indent=1) + "\n").encode())
    return out / TRANSFORMS


def _members(take: Take, rig: CameraRig, cameras: tuple[str, ...], index: np.ndarray,
             group: int) -> tuple[list[tuple[str, int]], list[str]]:
    """(camera, frame index) of each camera written, and the calibrated cameras with no frame in the group."""
    calibrated = [c for c in range(len(cameras)) if cameras[c] in rig.ids]
    if not calibrated:
        raise InputError(f"{take.path}: none of the take's cameras ({', '.join(cameras)}) is in the "
                         f"calibration ({', '.join(rig.ids)})")
    members = [(cameras[c], int(index[c])) for c in calibrated if index[c] >= 0]
    missing = [cameras[c] for c in calibrated if index[c] < 0]
    if not members:
        raise InputError(f"{take.path}: frame group {group} has no frame of a calibrated camera")
    return members, missing


def _check_rig(rig: CameraRig, out: Path) -> None:
    """Refuse what neither format can hold (skew), and ids that are no file name."""
    require_representable(rig, out / SPARSE, "COLMAP", lossy=False, skew=True, k3=False)
    plain_ids(rig, out / SPARSE, "COLMAP")
    bad = [cam for cam in rig.ids if cam in (".", "..") or "/" in cam or "\\" in cam]
    if bad:
        raise InputError(f"{out}: camera ids {bad} cannot name image files")


def _check_masks(rig: CameraRig, masks: Mapping[str, np.ndarray], out: Path) -> None:
    """Each camera written has a (H,W) bool mask; checked before anything is written."""
    for cam, (width, height) in zip(rig.ids, rig.size.astype(int)):
        if cam not in masks:
            raise InputError(f"{out}: masks were given but not for camera {cam!r} (nerfstudio needs a mask for "
                             "every frame or for none)")
        mask = np.asarray(masks[cam])
        if mask.dtype != bool or mask.shape != (height, width):
            raise InputError(f"{out}: the mask of camera {cam!r} is {mask.dtype} {mask.shape}, expected bool "
                             f"({height}, {width})")


def _refuse_existing(out: Path, force: bool) -> None:
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not force:
        raise OutputExists(f"{out}: exists and is not empty (use force=True to write over it)")


def _write_png(path: Path, image: np.ndarray) -> None:
    ok, data = cv2.imencode(".png", image)
    assert ok, f"{path}: cv2 could not encode a {image.dtype} {image.shape} image"  # a bug: callers pass uint8
    write_atomic(path, data.tobytes())
