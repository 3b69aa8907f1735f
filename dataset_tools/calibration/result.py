"""What a rig calibration returns: the cameras, how well each fits its data, and who is missing."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from manus_core.cameras import CameraRig
from manus_core.errors import ExtrinsicsError
from manus_core.rotations import rotvec_to_matrix

from .bundle import BundleState, Observations, unpack_intrinsics
from .intrinsics import coverage


@dataclass(frozen=True)
class CameraStats:
    """Per camera: reprojection RMS and median (px), observations, frames, image coverage."""

    rms_px: float
    median_px: float
    observations: int
    frames: int
    coverage: float
    intrinsics: dict = field(default_factory=dict)


@dataclass(frozen=True)
class RigCalibration:
    """The calibrated rig and how well it fits its data."""

    rig: CameraRig
    method: str
    stats: dict[str, CameraStats]
    obs: Observations
    residuals: np.ndarray
    outliers: int
    partial: bool = False
    missing: dict[str, str] = field(default_factory=dict)   # camera -> why it is not calibrated
    extra: dict = field(default_factory=dict)

    @property
    def rms_px(self) -> float:
        return float(np.sqrt(np.nanmean(np.sum(self.residuals**2, axis=1))))

    @property
    def median_px(self) -> float:
        return float(np.nanmedian(np.linalg.norm(self.residuals, axis=1)))


def camera_stats(ids: tuple[str, ...], obs: Observations, residuals: np.ndarray,
                 sizes: np.ndarray) -> dict[str, CameraStats]:
    """CameraStats of every camera (index c of obs.cam is ids[c]); NaN errors for a camera never seen."""
    out = {}
    err = np.linalg.norm(residuals, axis=1)
    for c, name in enumerate(ids):
        sel = obs.cam == c
        e = err[sel]
        out[name] = CameraStats(float(np.sqrt(np.nanmean(e**2))) if sel.any() else float("nan"),
                                float(np.nanmedian(e)) if sel.any() else float("nan"), int(sel.sum()),
                                len(np.unique(obs.frame[sel])), coverage(obs.xy[sel], tuple(sizes[c])))
    return out


def rig_from_state(ids, state: BundleState, sizes, stats: dict[str, CameraStats] | None = None) -> CameraRig:
    """The cameras of an adjusted state as a CameraRig (with their RMS when stats are given)."""
    K, dist = unpack_intrinsics(state.intr)
    rms = None if stats is None else [stats[i].rms_px for i in ids]
    return CameraRig(tuple(ids), K, dist, rotvec_to_matrix(state.cam_rvec), state.cam_t, np.asarray(sizes), rms)


def require_all(names: list[str], problems: dict[str, str], allow_partial: bool,
                error: type[ExtrinsicsError] = ExtrinsicsError) -> None:
    """Raise `error`, naming every camera and why, unless allow_partial (then the result leaves
    them out) and some camera is left."""
    left = len(set(names) - set(problems))
    if problems and (not allow_partial or not left):
        listed = "; ".join(f"camera {n}: {m}" for n, m in problems.items())
        hint = "fix the input" + ("" if allow_partial else " or pass --allow-partial for a result without them")
        raise error(f"{len(problems)} of {len(names)} cameras cannot be calibrated ({listed}); {hint}")
