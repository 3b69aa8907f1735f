"""How far a hand model's rest surface lies from the subject's true skin: scoring only.

The simulator stores the subject's rest skin and rest joints (ground_truth.h5, `hand/rest_surface`,
`hand/rest_joints`). A model's rest surface (MANUS-Hand's Gaussian centres, the template's points)
is brought onto them by the rigid motion that best matches the two skeletons' rest joints (their
bone lengths differ by the fit's error), and each point's distance to the skin is taken along the
normal of the nearest skin point: + outside, - inside. Fingers (points nearest a phalanx) and palm
(nearest a metacarpal, the wrist included) are reported apart: contact happens on the fingers,
and the palm is where the template lacks flesh.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from dataset_tools.calibration.colmap import similarity
from manus_core.ground_truth import TruthSkin


def surface_errors(points: np.ndarray, joints: np.ndarray, skin: TruthSkin,
                   true_joints: np.ndarray) -> dict[str, float]:
    """Mean absolute and median signed distance (mm) of rest-pose points (N,3), on a skeleton with
    rest joints (21,3), to the true skin with its rest joints (21,3): `fingers_mm`,
    `fingers_signed_mm`, `palm_mm`, `palm_signed_mm`, and `joints_mm`, the skeletons' misfit
    after the alignment (mean over joints)."""
    _, R, _ = similarity(joints, true_joints)
    t = true_joints.mean(0) - R @ joints.mean(0)
    moved = np.asarray(points, np.float64) @ R.T + t
    _, nearest = cKDTree(skin.points).query(moved)
    signed = ((moved - skin.points[nearest]) * skin.normals[nearest]).sum(1) * 1e3
    finger = skin.bone[nearest] % 4 != 0      # bones 0, 4, 8, 12 and 16 are the metacarpals
    out = {"joints_mm": float(np.linalg.norm(joints @ R.T + t - true_joints, axis=1).mean() * 1e3)}
    for name, part in (("fingers", finger), ("palm", ~finger)):
        out[f"{name}_mm"] = float(np.abs(signed[part]).mean()) if part.any() else float("nan")
        out[f"{name}_signed_mm"] = float(np.median(signed[part])) if part.any() else float("nan")
    return out
