"""COLMAP text models, read and written by pycolmap: cameras.txt + images.txt, with the rigs.txt
and frames.txt of COLMAP 3.12 / pycolmap 4 when present.

COLMAP's pixel origin is the corner of the first pixel, OpenCV's its centre: cx, cy move by 0.5 px
each way. Rotations go through scipy (manus_core.rotations) rather than Eigen, whose quaternion to
matrix round trip is off by up to 2e-15 where scipy's stays within 1e-15; pycolmap also keeps a
quaternion as written, unnormalized. A camera seen in several frames with different poses belongs
to a moving rig: its fixed calibration is then its pose in the rig (the rig's reference camera
becomes the world).
"""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path

import cv2  # noqa: F401  before pycolmap: a process that loads pycolmap's zlib first aborts in cv2's PNG writer
import numpy as np
import pycolmap

from manus_core.cameras import CameraRig
from manus_core.errors import CalibrationFileError
from manus_core.fileio import write_atomic
from manus_core.rotations import matrix_to_quat, quat_to_matrix

from .checks import build, plain_ids, require_representable, unit_scale

MODELS = {  # the models with an OpenCV equivalent -> parameter names, in COLMAP's order
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}


def _read_model(folder: Path, names: tuple[str, ...]) -> pycolmap.Reconstruction:
    """pycolmap's reading of the files `names` of `folder`. pycolmap reads a whole model, points3D.txt
    included; the cameras need no points, so an empty one stands in for it."""
    for name in names[:2]:
        if not (folder / name).is_file():
            raise CalibrationFileError(f"{folder / name}: missing from the COLMAP model")
    rec = pycolmap.Reconstruction()
    with tempfile.TemporaryDirectory(prefix="colmap-text-") as tmp:
        for name in names:
            os.symlink((folder / name).resolve(), Path(tmp) / name)
        (Path(tmp) / "points3D.txt").write_text("")
        try:
            rec.read_text(tmp)
        except (ValueError, IndexError, RuntimeError) as exc:
            # "[reconstruction_io_text.cc:148] Check failed: ...": the source line means nothing to a user
            reason = re.sub(r"^\[[^]]*\]\s*", "", str(exc)).strip()
            raise CalibrationFileError(f"{folder}: not a COLMAP text model pycolmap can read ({reason})") from None
    return rec


def _matrix(pose: pycolmap.Rigid3d, where: str) -> np.ndarray:
    """[R | t] (3,4) of a pycolmap pose, its quaternion normalized."""
    x, y, z, w = pose.rotation.quat
    try:
        R = quat_to_matrix(np.array([w, x, y, z]))
    except ValueError as exc:  # a zero quaternion
        raise CalibrationFileError(f"{where}: {exc}") from None
    return np.concatenate([R, np.asarray(pose.translation, np.float64)[:, None]], axis=1)


def _line_of(path: Path, camera_id: int) -> int:
    """The line of cameras.txt that defines camera_id (pycolmap's errors name none)."""
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        fields = line.split()
        if fields and fields[0].isdigit() and int(fields[0]) == camera_id:
            return number
    return 0


def _intrinsics(camera: pycolmap.Camera, path: Path) -> tuple[list, list, tuple[int, int]]:
    """(K, dist, (width, height)) of a COLMAP camera in OpenCV's convention."""
    model = camera.model.name
    if model not in MODELS:
        raise CalibrationFileError(f"{path}:{_line_of(path, camera.camera_id)}: camera model {model!r} is not "
                                   f"supported (supported: {', '.join(MODELS)})")
    p = dict(zip(MODELS[model], map(float, camera.params)))
    if any(p.get(k, 0.0) != 0.0 for k in ("k4", "k5", "k6")):
        raise CalibrationFileError(f"{path}:{_line_of(path, camera.camera_id)}: FULL_OPENCV with k4..k6 "
                                   "(rational model) is not supported")
    fx, fy = p.get("fx", p.get("f")), p.get("fy", p.get("f"))
    K = [[fx, 0.0, p["cx"] - 0.5], [0.0, fy, p["cy"] - 0.5], [0.0, 0.0, 1.0]]
    dist = [p.get("k1", 0.0), p.get("k2", 0.0), p.get("p1", 0.0), p.get("p2", 0.0), p.get("k3", 0.0)]
    return K, dist, (camera.width, camera.height)


def _rigs(folder: Path, images: dict[int, tuple]) -> tuple[dict[int, np.ndarray | None], dict[int, int]]:
    """sensor_from_rig (3,4) per camera id (None where rigs.txt gives no pose) and its rig id, from
    rigs.txt and frames.txt; raises where an image's pose in images.txt disagrees with its frame's."""
    rec = _read_model(folder, ("cameras.txt", "images.txt", "rigs.txt", "frames.txt"))
    sensor_from_rig, rig_of = {}, {}
    for rig in rec.rigs.values():
        sensors = [(rig.ref_sensor_id, np.eye(3, 4))]
        sensors += [(s, None if p is None else _matrix(p, f"{folder / 'rigs.txt'}: rig {rig.rig_id}"))
                    for s, p in rig.non_ref_sensors.items()]
        for sensor, pose in sensors:
            if sensor.type == pycolmap.SensorType.CAMERA:
                sensor_from_rig[sensor.id], rig_of[sensor.id] = pose, rig.rig_id
    for image in rec.images.values():
        if image.has_pose and image.image_id in images and sensor_from_rig.get(image.camera_id) is not None:
            where = f"{folder / 'frames.txt'}: image {image.name}"
            if np.abs(_matrix(image.cam_from_world(), where) - images[image.image_id][0]).max() > 1e-6:
                raise CalibrationFileError(f"{folder / 'images.txt'}: the pose of {image.name} disagrees with "
                                           "rigs.txt and frames.txt")
    return sensor_from_rig, rig_of


def read_colmap(folder: Path, units: str | None) -> CameraRig:
    """One camera per COLMAP camera, named after its images' folder (or its one image)."""
    cameras_path, images_path = folder / "cameras.txt", folder / "images.txt"
    rec = _read_model(folder, ("cameras.txt", "images.txt"))
    images = {im.image_id: (_matrix(im.cam_from_world(), f"{images_path}: image {im.name}"), im.camera_id, im.name)
              for im in sorted(rec.images.values(), key=lambda im: im.image_id) if im.has_pose}
    if not images:
        raise CalibrationFileError(f"{images_path}: holds no registered images")
    scale = unit_scale(units, str(folder))
    sensor_from_rig, rig_of = {}, {}
    if (folder / "rigs.txt").is_file() and (folder / "frames.txt").is_file():
        sensor_from_rig, rig_of = _rigs(folder, images)

    by_camera: dict[int, list] = {}
    for image in images.values():
        by_camera.setdefault(image[1], []).append(image)
    moving = [c for c, group in by_camera.items()
              if any(np.abs(g[0] - group[0][0]).max() > 1e-9 for g in group[1:])]
    use_rig = bool(moving) and all(sensor_from_rig.get(c) is not None for c in by_camera) \
        and len({rig_of[c] for c in by_camera}) == 1
    if moving and not use_rig:
        group = by_camera[moving[0]]
        raise CalibrationFileError(f"{images_path}: camera {moving[0]} has images with different poses "
                                   f"({group[0][2]}, {group[1][2]}) and no common rig; keep one frame per camera")
    ids, K, dist, R, t, size = [], [], [], [], [], []
    for camera_id in sorted(by_camera):
        group = by_camera[camera_id]
        pose = sensor_from_rig[camera_id] if use_rig else group[0][0]
        folders = {name.rsplit("/", 1)[0] for _, _, name in group if "/" in name}
        if len(folders) == 1 and all("/" in g[2] for g in group):
            ids.append(folders.pop())
        elif len(group) == 1:
            ids.append(Path(group[0][2]).stem)
        else:
            ids.append(str(camera_id))
        k, d, wh = _intrinsics(rec.cameras[camera_id], cameras_path)
        K.append(k)
        dist.append(d)
        R.append(pose[:, :3])
        t.append(pose[:, 3] * scale)
        size.append(wh)
    if len(set(ids)) != len(ids):
        ids = [str(c) for c in sorted(by_camera)]
    return build(str(folder), ids, K, dist, R, t, size)


def write_colmap(rig: CameraRig, folder: Path, lossy: bool, image_suffix: str = ".jpg") -> None:
    """The rig as a COLMAP text model in `folder`: one camera (OPENCV, or FULL_OPENCV when k3 is
    not 0), one image CAMERA_ID + image_suffix and one trivial rig and frame per camera; each file
    atomically."""
    require_representable(rig, folder, "COLMAP", lossy, skew=True, k3=False)
    plain_ids(rig, folder, "COLMAP")
    rec = pycolmap.Reconstruction()
    for i, cam_id in enumerate(rig.ids):
        K, d = rig.K[i], rig.dist[i]
        params = [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5, *d[:4]]
        model = "OPENCV"
        if d[4] != 0:
            model, params = "FULL_OPENCV", params + [d[4], 0.0, 0.0, 0.0]
        rec.add_camera_with_trivial_rig(pycolmap.Camera(model=model, width=int(rig.size[i, 0]),
                                                        height=int(rig.size[i, 1]), params=params, camera_id=i + 1))
        q = matrix_to_quat(rig.R[i])
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(q[[1, 2, 3, 0]]), rig.t[i])  # pycolmap takes x, y, z, w
        image = pycolmap.Image(name=f"{cam_id}{image_suffix}", camera_id=i + 1, image_id=i + 1)
        rec.add_image_with_trivial_frame(image, pose)
    with tempfile.TemporaryDirectory(prefix="colmap-text-") as tmp:
        rec.write_text(tmp)
        for path in sorted(Path(tmp).iterdir()):
            write_atomic(folder / path.name, path.read_bytes())
