"""The documented Python surface of manus-capture (DESIGN.md, "Public API").

    from manus_capture.api import load_cameras, triangulate, one_euro, HandSkeleton, fit_hand

Names resolve on first use, so importing this module stays cheap (torch and pycolmap load only
with the pieces that need them).
"""

from __future__ import annotations

import importlib

_EXPORTS: dict[str, str] = {
    "CameraRig": "manus_core.cameras",
    "load_cameras": "dataset_tools.calibration.formats",
    "triangulate": "dataset_tools.triangulation",
    "one_euro": "dataset_tools.one_euro",
    "HandSkeleton": "manus_core.skeleton",
    "fit_hand": "dataset_tools.hand.ik",
    "read_dataset": "manus_core.dataset",
    "frame_groups": "dataset_tools.sync",
    "hand_keypoint_detector": "dataset_tools.keypoints",
    "Detector": "dataset_tools.keypoints",
    "rasterize": "manus_capture.splat",
    "load_rig": "manus_core.rig_config",
    "RigConfig": "manus_core.rig_config",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'manus_capture.api' has no attribute {name!r}")
    value = getattr(importlib.import_module(_EXPORTS[name]), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return __all__
