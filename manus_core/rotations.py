"""Rotations as the project passes them around: matrices (...,3,3), Rodrigues vectors (...,3) and
unit quaternions (w, x, y, z), the order COLMAP and MANUS files write them in.

Batched and vectorized (scipy's Rotation underneath); every function takes and returns float64.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def rotvec_to_matrix(r: np.ndarray) -> np.ndarray:
    """Rodrigues vectors (...,3) to rotation matrices (...,3,3)."""
    r = np.asarray(r, np.float64)
    return Rotation.from_rotvec(r.reshape(-1, 3)).as_matrix().reshape(r.shape[:-1] + (3, 3))


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (...,3,3) to Rodrigues vectors (...,3)."""
    R = np.asarray(R, np.float64)
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(R.shape[:-2] + (3,))


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Quaternions (w, x, y, z) (...,4), normalized first, to rotation matrices (...,3,3).

    Raises ValueError for a zero quaternion.
    """
    q = np.asarray(q, np.float64)
    return Rotation.from_quat(q.reshape(-1, 4), scalar_first=True).as_matrix().reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (...,3,3) to unit quaternions (w, x, y, z) (...,4) with w >= 0."""
    R = np.asarray(R, np.float64)
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat(canonical=True, scalar_first=True)
    return q.reshape(R.shape[:-2] + (4,))


def mean_rotation(Rs: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of rotations (N,3,3) after dropping those far from the median estimate."""
    rot = Rotation.from_matrix(Rs)
    first = rot.mean()
    angle = (first.inv() * rot).magnitude()
    keep = angle <= max(3 * np.median(angle), np.deg2rad(1.0))
    return rot[keep].mean().as_matrix()


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """Angle of Ra^T Rb in degrees, batched."""
    cos = (np.einsum("...ji,...ji->...", Ra, Rb) - 1) / 2
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))
