"""The 26-DOF hand skeleton: joint order, degrees of freedom, joint limits, forward kinematics.

One implementation serves numpy (IK, the simulated rig) and torch (the Gaussian hand): every
function picks its array namespace from the input's type and uses only operations both share, so
the torch path is differentiable and the numpy path needs no torch import.

Canonical (rest) frame of the right hand: wrist at the origin, fingers along +y, palm facing -z,
thumb on the -x side. Flexion (positive) curls a finger towards the palm (-z); abduction
(positive) turns it about the finger's +z axis, towards the thumb side. All 26 angles zero give a
flat, naturally spread open hand. See docs/hand.md.
"""

from __future__ import annotations

from functools import cached_property
from typing import Any

import numpy as np

FINGERS = ("thumb", "index", "middle", "ring", "pinky")
_THUMB_JOINTS = ("cmc", "mcp", "ip", "tip")
_FINGER_JOINTS = ("mcp", "pip", "dip", "tip")
JOINT_NAMES = ("wrist",) + tuple(
    f"{f}_{j}" for f in FINGERS for j in (_THUMB_JOINTS if f == "thumb" else _FINGER_JOINTS)
)
PARENTS = np.array([-1] + [0 if k == 0 else 1 + 4 * f + k - 1 for f in range(5) for k in range(4)])
# Bone b runs from PARENTS[b + 1] to joint b + 1; bones 4f are the metacarpal segments that
# move rigidly with the palm (for the thumb: wrist -> CMC), 4f+1..4f+3 are the moving segments.
BONES = np.stack([PARENTS[1:], np.arange(1, 21)], axis=1)
FINGERTIPS = (4, 8, 12, 16, 20)
FINGER_BONES = tuple(tuple(range(4 * f, 4 * f + 4)) for f in range(5))

_DOF_SUFFIXES = {
    "thumb": ("cmc_flex", "cmc_abd", "mcp_flex", "ip_flex"),
    "finger": ("mcp_flex", "mcp_abd", "pip_flex", "dip_flex"),
}
DOF_NAMES = ("rot_x", "rot_y", "rot_z", "trans_x", "trans_y", "trans_z") + tuple(
    f"{f}_{s}" for f in FINGERS for s in _DOF_SUFFIXES["thumb" if f == "thumb" else "finger"]
)
N_DOF = 26

# Conservative limits of articulated-ICP hand tracking (Tagliasacchi et al. 2015), radians.
_ABDUCTION_LIMITS = {"thumb": (-0.3, 0.3), "index": (-0.5, 0.4), "middle": (-0.3, 0.3),
                     "ring": (-0.3, 0.3), "pinky": (-0.5, 0.3)}
_FLEXION_LIMITS = (-0.1, 1.5)


def _default_limits() -> tuple[np.ndarray, np.ndarray]:
    lower = np.full(N_DOF, -np.inf)
    upper = np.full(N_DOF, np.inf)
    for f, name in enumerate(FINGERS):
        base = 6 + 4 * f
        for k in (0, 2, 3):
            lower[base + k], upper[base + k] = _FLEXION_LIMITS
        lower[base + 1], upper[base + 1] = _ABDUCTION_LIMITS[name]
    return lower, upper


LOWER, UPPER = _default_limits()

# An average adult hand (metres): wrist->MCP (thumb: wrist->CMC, CMC->MCP), then the phalanges;
# the last bone of each finger ends at the fingertip surface, as the keypoint does.
DEFAULT_BONE_LENGTHS = np.array([
    0.036, 0.044, 0.033, 0.030,   # thumb
    0.085, 0.043, 0.025, 0.023,   # index
    0.083, 0.047, 0.029, 0.024,   # middle
    0.078, 0.044, 0.028, 0.024,   # ring
    0.072, 0.034, 0.020, 0.022,   # pinky
])


def _unit(v: Any) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def _np_rot(axis: str, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


# Rest direction of each metacarpal segment (wrist -> MCP; thumb: wrist -> CMC). The MCPs fan
# out over ~7.5 cm of knuckle line; the thumb's CMC sits radial and a little palmar.
META_DIRS = np.stack([
    _unit([-0.70, 0.70, -0.20]),
    _unit([-0.30, 1.00, 0.0]),
    _unit([-0.085, 1.00, 0.0]),
    _unit([0.14, 1.00, 0.0]),
    _unit([0.40, 1.00, 0.0]),
])
# Rest frame of each finger's moving chain (columns: local x, y = bone direction, z). The four
# fingers are spread slightly about +z. The thumb points ~45 deg out to the side and a little
# palmar, and is rolled about its own axis so that its local -z (flexion direction) faces across
# the palm: flexing the thumb then brings it over the palm towards the little finger.
REST_FRAMES = np.stack([
    _np_rot("z", 0.80) @ _np_rot("x", -0.20) @ _np_rot("y", -0.95),
    _np_rot("z", 0.12),
    _np_rot("z", 0.02),
    _np_rot("z", -0.08),
    _np_rot("z", -0.20),
])


def _namespace(x: Any):
    """(xp, const): the array module of x and a converter of constants to x's dtype/device."""
    if type(x).__module__.split(".")[0] == "torch":
        import torch

        return torch, lambda c: torch.as_tensor(c, dtype=x.dtype, device=x.device)
    dtype = x.dtype if np.issubdtype(x.dtype, np.floating) else np.float64
    return np, lambda c: np.asarray(c, dtype=dtype)


def _as_array(x: Any) -> Any:
    if type(x).__module__.split(".")[0] == "torch":
        return x
    x = np.asarray(x)
    return x if np.issubdtype(x.dtype, np.floating) else x.astype(np.float64)


def _mat(xp, entries: list, shape: tuple) -> Any:
    return xp.stack(entries, -1).reshape(tuple(shape) + (3, 3))


def rot_x(angle: Any) -> Any:
    """Rotation matrices (...,3,3) about +x by angle (...)."""
    angle = _as_array(angle)
    xp, _ = _namespace(angle)
    c, s, o, z = xp.cos(angle), xp.sin(angle), xp.ones_like(angle), xp.zeros_like(angle)
    return _mat(xp, [o, z, z, z, c, -s, z, s, c], angle.shape)


def rot_z(angle: Any) -> Any:
    """Rotation matrices (...,3,3) about +z by angle (...)."""
    angle = _as_array(angle)
    xp, _ = _namespace(angle)
    c, s, o, z = xp.cos(angle), xp.sin(angle), xp.ones_like(angle), xp.zeros_like(angle)
    return _mat(xp, [c, -s, z, s, c, z, z, z, o], angle.shape)


def rodrigues(rvec: Any) -> Any:
    """Rotation vectors (...,3) -> matrices (...,3,3), numpy or torch.

    Safe at zero in torch: below a tiny angle the series expansion is taken, and the other branch
    of the `where` is fed a harmless angle so that no NaN leaks into the gradient.
    """
    rvec = _as_array(rvec)
    xp, const = _namespace(rvec)
    th2 = (rvec * rvec).sum(-1)
    small = th2 < 1e-8
    th = xp.sqrt(xp.where(small, const(1.0), th2))
    a = xp.where(small, 1.0 - th2 / 6.0, xp.sin(th) / th)
    half = xp.sin(th / 2.0) / th
    # 2 sin^2(th/2)/th^2 rather than (1-cos th)/th^2: no cancellation in float32.
    b = xp.where(small, 0.5 - th2 / 24.0, 2.0 * half * half)
    x, y, z = rvec[..., 0], rvec[..., 1], rvec[..., 2]
    zero = xp.zeros_like(x)
    k = _mat(xp, [zero, -z, y, z, zero, -x, -y, x, zero], x.shape)
    return const(np.eye(3)) + a[..., None, None] * k + b[..., None, None] * (k @ k)


def _mv(m: Any, v: Any) -> Any:
    return (m @ v[..., None])[..., 0]


def _swap(m: Any) -> Any:
    """Transpose of the last two axes, in either namespace."""
    return m.transpose(-1, -2) if type(m).__module__.split(".")[0] == "torch" else np.swapaxes(m, -1, -2)


class HandSkeleton:
    """Forward kinematics of the 26-DOF hand with per-subject bone lengths and joint limits.

    forward / bone_transforms / clamp accept numpy arrays or torch tensors of shape (...,26) and
    return the same type; batch dimensions are vectorized.
    """

    def __init__(self, bone_lengths: Any = None, lower: Any = None, upper: Any = None) -> None:
        self.bone_lengths = np.array(DEFAULT_BONE_LENGTHS if bone_lengths is None else bone_lengths,
                                     dtype=np.float64)
        self.lower = np.array(LOWER if lower is None else lower, dtype=np.float64)
        self.upper = np.array(UPPER if upper is None else upper, dtype=np.float64)
        if self.bone_lengths.shape != (20,) or np.any(self.bone_lengths <= 0):
            raise ValueError(f"bone_lengths must be 20 positive lengths, got shape {self.bone_lengths.shape}")
        if self.lower.shape != (N_DOF,) or self.upper.shape != (N_DOF,) or np.any(self.lower > self.upper):
            raise ValueError("lower/upper must be (26,) with lower <= upper")

    def _lengths(self, angles: Any, bone_lengths: Any) -> Any:
        _, const = _namespace(angles)
        return const(self.bone_lengths) if bone_lengths is None else bone_lengths

    def _chain(self, angles: Any, bone_lengths: Any) -> tuple[list, list]:
        """Posed joints (21 arrays (...,3)) and world rotations of the 20 bone frames."""
        xp, const = _namespace(angles)
        lengths = self._lengths(angles, bone_lengths)
        rg = rodrigues(angles[..., 0:3])
        wrist = angles[..., 3:6]
        joints = [wrist] + [None] * 20
        frames = [None] * 20
        for f in range(5):
            b0, d = 4 * f, 6 + 4 * f
            frames[b0] = rg
            joints[b0 + 1] = wrist + _mv(rg, const(META_DIRS[f])) * lengths[..., b0, None]
            frame = rg @ const(REST_FRAMES[f]) @ rot_z(angles[..., d + 1]) @ rot_x(-angles[..., d])
            for k, dof in ((1, None), (2, d + 2), (3, d + 3)):
                if dof is not None:
                    frame = frame @ rot_x(-angles[..., dof])
                frames[b0 + k] = frame
                joints[b0 + k + 1] = joints[b0 + k] + frame[..., :, 1] * lengths[..., b0 + k, None]
        return joints, frames

    def forward(self, angles: Any, bone_lengths: Any = None) -> Any:
        """Joint positions (...,21,3) for angles (...,26); bone_lengths (...,20) overrides the subject's."""
        angles = _as_array(angles)
        xp, _ = _namespace(angles)
        joints, _ = self._chain(angles, bone_lengths)
        return xp.stack(joints, -2)

    def rest_joints(self, bone_lengths: Any = None) -> np.ndarray:
        """Joints (21,3) of the rest pose (all angles zero)."""
        return self.forward(np.zeros(N_DOF), bone_lengths)

    def bone_transforms(self, angles: Any, bone_lengths: Any = None) -> tuple[Any, Any]:
        """Rigid motion of every bone from the rest pose: (R (...,20,3,3), t (...,20,3)).

        A point x attached to bone b in the rest frame moves to R[b] @ x + t[b]; this is what
        linear blend skinning and the simulated hand surface use.
        """
        angles = _as_array(angles)
        xp, const = _namespace(angles)
        joints, frames = self._chain(angles, bone_lengths)
        if bone_lengths is None and xp is np:
            # the subject's own rest pose, the same for every call (bone_lengths is set once, in __init__)
            rest = self._rest_joints
        else:
            rest = self._chain(xp.zeros_like(angles[..., :N_DOF]), bone_lengths)[0]
        rs, ts = [], []
        for b in range(20):
            rest_frame = np.eye(3) if b % 4 == 0 else REST_FRAMES[b // 4]
            r = frames[b] @ const(rest_frame.T)
            start = int(BONES[b, 0])
            rs.append(r)
            ts.append(joints[start] - _mv(r, rest[start]))
        return xp.stack(rs, -3), xp.stack(ts, -2)

    @cached_property
    def _rest_joints(self) -> np.ndarray:
        return self.rest_joints()

    def clamp(self, angles: Any) -> Any:
        """Angles with every DOF inside [lower, upper]."""
        angles = _as_array(angles)
        xp, const = _namespace(angles)
        return xp.minimum(xp.maximum(angles, const(self.lower)), const(self.upper))

    def within_limits(self, angles: Any, tol: float = 1e-9) -> np.ndarray:
        """Bool (...,): every DOF of the pose inside the limits (numpy input)."""
        angles = np.asarray(angles)
        return np.all((angles >= self.lower - tol) & (angles <= self.upper + tol), axis=-1)
