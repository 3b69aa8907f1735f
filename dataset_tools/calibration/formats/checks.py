"""What every camera file reader and writer checks, so that no format changes a camera silently.

Readers build their CameraRig through `build`, which names the file and the camera when a value is
not finite, a rotation is not a rotation or a camera matrix is invalid. Writers refuse what their
format cannot hold (`require_representable`) unless lossy, and ids their files cannot store.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from manus_core.cameras import CameraRig
from manus_core.errors import CalibrationFileError

UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}


def build(source: str, ids, K, dist, R, t, size, rms=None) -> CameraRig:
    """A CameraRig from per-camera lists, checked; CalibrationFileError names `source` and the camera."""
    if not len(ids):
        raise CalibrationFileError(f"{source}: holds no cameras")
    try:
        rig = CameraRig(tuple(ids), K, dist, R, t, size, rms)
    except ValueError as exc:
        raise CalibrationFileError(f"{source}: {exc}") from None
    for name in ("K", "dist", "R", "t", "size"):
        bad = ~np.isfinite(getattr(rig, name)).reshape(len(rig), -1).all(axis=1)
        if bad.any():
            raise CalibrationFileError(f"{source}: camera {rig.ids[int(np.argmax(bad))]!r} has a non-finite {name}")
    ortho = np.abs(np.einsum("cji,cjk->cik", rig.R, rig.R) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(rig.R)
    bad = (ortho > 1e-6) | (det < 0)
    if bad.any():
        i = int(np.argmax(bad))
        raise CalibrationFileError(f"{source}: camera {rig.ids[i]!r} has a rotation that is not a rotation "
                                   f"(|R'R - I| = {ortho[i]:.2g}, det = {det[i]:.3f})")
    bad = (rig.K[:, 0, 0] <= 0) | (rig.K[:, 1, 1] <= 0) | (np.abs(rig.K[:, 2] - [0, 0, 1]).max(axis=1) > 0)
    if bad.any():
        raise CalibrationFileError(f"{source}: camera {rig.ids[int(np.argmax(bad))]!r} has an invalid camera "
                                   "matrix (focal lengths must be > 0 and the last row [0, 0, 1])")
    return rig


def dist5(values, source: str, cam: str) -> list[float]:
    """Distortion coefficients as OpenCV's five (k1, k2, p1, p2, k3), zero-padded; more that are
    not zero (a rational or thin-prism model) are refused."""
    d = [float(v) for v in np.asarray(values, dtype=np.float64).ravel()]
    if any(v != 0 for v in d[5:]):
        raise CalibrationFileError(f"{source}: camera {cam!r} has {len(d)} distortion coefficients; only the "
                                   "5-coefficient OpenCV model (k1, k2, p1, p2, k3) is supported")
    return (d + [0.0] * 5)[:5]


def unit_scale(units: str | None, source: str) -> float:
    """Metres per unit of a file's translations (None: metres)."""
    units = "m" if units is None else units
    if units not in UNITS:
        raise CalibrationFileError(f"{source}: unknown length unit {units!r}; use one of {', '.join(UNITS)}")
    return UNITS[units]


def require_representable(rig: CameraRig, path: Path, fmt: str, lossy: bool, skew: bool, k3: bool) -> None:
    """Refuse a rig with skew (skew=True: the format has none) or k3 (k3=True) unless lossy."""
    if lossy:
        return
    if skew and np.any(rig.K[:, 0, 1] != 0):
        i = int(np.argmax(rig.K[:, 0, 1] != 0))
        raise CalibrationFileError(f"{path}: the {fmt} format has no skew but camera {rig.ids[i]!r} has "
                                   f"skew {float(rig.K[i, 0, 1])!r}; pass lossy=True to drop it")
    if k3 and np.any(rig.dist[:, 4] != 0):
        i = int(np.argmax(rig.dist[:, 4] != 0))
        raise CalibrationFileError(f"{path}: the {fmt} format holds k1 k2 p1 p2 only but camera {rig.ids[i]!r} "
                                   f"has k3 = {float(rig.dist[i, 4])!r}; pass lossy=True to drop it")


def plain_ids(rig: CameraRig, path: Path, fmt: str) -> None:
    """Refuse camera ids a whitespace-separated format cannot hold."""
    bad = [i for i in rig.ids if not i or re.search(r"\s", i)]
    if bad:
        raise CalibrationFileError(f"{path}: the {fmt} format needs camera ids without whitespace, got {bad}")
