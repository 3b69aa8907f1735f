"""anipose calibration.toml and caliscope camera_array.toml (and caliscope's older config.toml).

anipose writes [cam_N] tables, caliscope [cameras.N]; both hold matrix, distortions, a Rodrigues
rotation (or a matrix), a translation in the board's unit (`units=`) and the image size.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np

from manus_core.cameras import CameraRig
from manus_core.errors import CalibrationFileError
from manus_core.rotations import rotvec_to_matrix

from .checks import build, dist5, unit_scale


def _rotation(value, source: str, what: str) -> np.ndarray:
    """A 3x3 matrix or a Rodrigues 3-vector to a rotation matrix."""
    a = np.asarray(value, dtype=np.float64)
    if a.size == 3:
        return rotvec_to_matrix(a.reshape(3))
    if a.size == 9:
        return a.reshape(3, 3)
    raise CalibrationFileError(f"{source}: {what} has {a.size} numbers; expected a 3x3 matrix or a Rodrigues 3-vector")


def read_toml(path: Path, units: str | None) -> CameraRig:
    """The cameras of an anipose or caliscope file; cameras caliscope marks `ignore` are left out."""
    try:
        doc = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise CalibrationFileError(f"{path}: not TOML ({exc})") from None
    if isinstance(doc.get("cameras"), dict):  # caliscope camera_array.toml: [cameras.N]
        tables = [(str(k), v) for k, v in doc["cameras"].items()]
    else:  # anipose calibration.toml and caliscope's older config.toml: [cam_N]
        tables = [(k, v) for k, v in doc.items() if k.startswith("cam_") and isinstance(v, dict)]
    if not tables:
        raise CalibrationFileError(f"{path}: no camera tables ([cam_0] as anipose writes, "
                                   "or [cameras.0] as caliscope does)")
    scale = unit_scale(units, str(path))
    ids, K, dist, R, t, size, rms = [], [], [], [], [], [], []
    for key, cam in tables:
        if cam.get("ignore", False):  # caliscope's switch for cameras left out of a session
            continue
        cam_id = str(cam.get("name", cam.get("cam_id", key.removeprefix("cam_"))))
        if cam.get("fisheye", False):
            raise CalibrationFileError(f"{path}: camera {cam_id!r} is a fisheye camera; "
                                       "only the pinhole model is supported")
        missing = [f for f in ("matrix", "distortions", "rotation", "translation", "size") if f not in cam]
        if missing:
            raise CalibrationFileError(f"{path}: camera {cam_id!r} has no {', '.join(missing)}"
                                       + (" (not calibrated yet?)" if "rotation" in missing else ""))
        ids.append(cam_id)
        K.append(cam["matrix"])
        dist.append(dist5(cam["distortions"], str(path), cam_id))
        R.append(_rotation(cam["rotation"], str(path), f"camera {cam_id!r} rotation"))
        t.append(np.asarray(cam["translation"], dtype=np.float64).reshape(-1) * scale)
        size.append(cam["size"])
        rms.append(float(cam["error"]) if "error" in cam else np.nan)
    return build(str(path), ids, K, dist, R, t, size, rms)
