"""cameras.json, this project's calibration file (CameraRig.save writes it); its unit is recorded
in "units". A JSON file with CMU Panoptic's fields is handed to panoptic.py."""

from __future__ import annotations

import json
from pathlib import Path

from manus_core.cameras import CameraRig
from manus_core.errors import CalibrationFileError

from .checks import build, unit_scale
from .panoptic import looks_panoptic, read_panoptic


def read_json(path: Path) -> CameraRig:
    """cameras.json (its translations converted to metres) or, recognised by its fields, CMU Panoptic."""
    try:
        doc = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CalibrationFileError(f"{path}: not JSON ({exc})") from None
    if isinstance(doc, dict) and ("calibDataSource" in doc or looks_panoptic(doc)):
        return read_panoptic(doc, path)
    rig = CameraRig.from_json(doc, str(path))
    scale = unit_scale(doc.get("units", "m"), str(path))
    return build(str(path), rig.ids, rig.K, rig.dist, rig.R, rig.t * scale, rig.size, rig.rms_px)
