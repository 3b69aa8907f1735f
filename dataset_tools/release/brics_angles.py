"""Our 26 joint angles and a MANUS release's joint_angles files, both ways (docs/datasets.md).

A release pose is {"translation": [3], "angles": 21 x 3}: row 0 the hand's rotation, row 1 + b
bone b's rotation in its own rest frame, each as Blender's 'XYZ' Euler angles in radians
(R = Rz @ Ry @ Rx). Their skeleton's degrees of freedom are z (flexion) on every phalanx and x
(abduction) besides at the base of each finger and on the thumb; the metacarpal rows are zero.
Our 26 DOF map onto them one to one:

    rotation vector (0:3)  <-> row 0 as a matrix (Euler XYZ)     translation (3:6) <-> translation
    finger f = index..pinky: mcp_flex <-> row 4f+2 z, mcp_abd <-> row 4f+2 x,
                             pip_flex <-> row 4f+3 z, dip_flex <-> row 4f+4 z
    thumb: cmc_flex <-> row 2 z, cmc_abd <-> row 2 x, mcp_flex <-> row 3 z, ip_flex <-> row 4 z

Row 1 (their wrist-to-CMC thumb bone, which moves; ours is rigid with the palm) is written zero
and ignored when read. The mapping is exact for files this toolkit writes. On MANUS's own files
the angles are relative to their Blender rest pose, which is not in the release, so the import
fits our skeleton to their keypoints_3d wherever those exist and uses the mapping only where
they do not (the import summary gives the difference between the two).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from manus_core.rotations import matrix_to_rotvec, rotvec_to_matrix

# (our DOF index, release row, axis 0=x 2=z)
_PAIRS = [(6, 2, 2), (7, 2, 0), (8, 3, 2), (9, 4, 2)] + [
    (6 + 4 * f + k, 4 * f + r, axis) for f in range(1, 5)
    for k, r, axis in ((0, 2, 2), (1, 2, 0), (2, 3, 2), (3, 4, 2))]
_OURS = np.array([p[0] for p in _PAIRS])
_ROWS = np.array([p[1] for p in _PAIRS])
_AXES = np.array([p[2] for p in _PAIRS])


def euler_xyz_to_matrix(e: np.ndarray) -> np.ndarray:
    """Blender 'XYZ' Euler angles (...,3) to matrices Rz @ Ry @ Rx (...,3,3)."""
    e = np.asarray(e, np.float64)
    return Rotation.from_euler("xyz", e.reshape(-1, 3)).as_matrix().reshape(e.shape[:-1] + (3, 3))


def matrix_to_euler_xyz(R: np.ndarray) -> np.ndarray:
    R = np.asarray(R, np.float64)
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_euler("xyz").reshape(R.shape[:-2] + (3,))


def to_release(angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Our angles (T,26) as the release's (translation (T,3), angles (T,21,3)); a NaN angle stays NaN."""
    angles = np.asarray(angles, np.float64)
    eulers = np.zeros(angles.shape[:-1] + (21, 3))
    turned = np.isfinite(angles[..., 0:3]).all(-1)
    eulers[~turned, 0] = np.nan
    if turned.any():
        eulers[turned, 0] = matrix_to_euler_xyz(rotvec_to_matrix(angles[turned, 0:3]))
    eulers[..., _ROWS, _AXES] = angles[..., _OURS]
    return angles[..., 3:6].copy(), eulers


def from_release(translation: np.ndarray, eulers: np.ndarray) -> np.ndarray:
    """The release's (translation (T,3), angles (T,21,3)) as our angles (T,26)."""
    translation, eulers = np.asarray(translation, np.float64), np.asarray(eulers, np.float64)
    out = np.full(translation.shape[:-1] + (26,), np.nan)
    turned = np.isfinite(eulers[..., 0, :]).all(-1)
    if turned.any():
        out[turned, 0:3] = matrix_to_rotvec(euler_xyz_to_matrix(eulers[turned, 0]))
    out[..., 3:6] = translation
    out[..., _OURS] = eulers[..., _ROWS, _AXES]
    return out
