"""CMU Panoptic calibration JSON (calibration_<session>.json): K, distCoef, R, t in centimetres,
one camera per entry named by 'name'. Recognised by its fields; cameras.json is read elsewhere."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from manus_core.cameras import CameraRig
from manus_core.errors import CalibrationFileError

from .checks import UNITS, build, dist5


def looks_panoptic(doc) -> bool:
    """Whether a parsed JSON document has Panoptic's camera entries (distCoef)."""
    cams = doc.get("cameras") if isinstance(doc, dict) else None
    return isinstance(cams, list) and bool(cams) and isinstance(cams[0], dict) and "distCoef" in cams[0]


def read_panoptic(doc: dict, path: Path) -> CameraRig:
    """The cameras of a parsed Panoptic calibration, in metres."""
    ids, K, dist, R, t, size = [], [], [], [], [], []
    try:
        for cam in doc["cameras"]:
            ids.append(str(cam["name"]))
            K.append(cam["K"])
            dist.append(dist5(cam["distCoef"], str(path), cam["name"]))
            R.append(cam["R"])
            t.append(np.asarray(cam["t"], dtype=np.float64).reshape(3) * UNITS["cm"])
            size.append(cam["resolution"])
    except (KeyError, TypeError, ValueError) as exc:
        raise CalibrationFileError(f"{path}: not a CMU Panoptic calibration ({exc!r} in camera {len(ids)})") from None
    return build(str(path), ids, K, dist, R, t, size)
