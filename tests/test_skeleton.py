"""The 26-DOF skeleton: kinematics invariants, numpy/torch agreement, gradients, limits."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from manus_core.skeleton import (
    BONES,
    DEFAULT_BONE_LENGTHS,
    DOF_NAMES,
    FINGERTIPS,
    JOINT_NAMES,
    LOWER,
    PARENTS,
    UPPER,
    HandSkeleton,
    rodrigues,
)


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    """Poses within the joint limits with arbitrary global rotation and translation."""
    rng = np.random.default_rng(seed)
    a = np.zeros((n, 26))
    a[:, :3] = rng.normal(scale=1.2, size=(n, 3))
    a[:, 3:6] = rng.uniform(-0.3, 0.3, size=(n, 3))
    a[:, 6:] = rng.uniform(LOWER[6:], UPPER[6:], size=(n, 20))
    return a


def test_tables_are_consistent():
    assert len(JOINT_NAMES) == 21 and len(DOF_NAMES) == 26 and PARENTS[0] == -1
    assert JOINT_NAMES[4] == "thumb_tip" and JOINT_NAMES[8] == "index_tip" and JOINT_NAMES[20] == "pinky_tip"
    assert np.array_equal(BONES[:, 1], np.arange(1, 21)) and np.array_equal(BONES[:, 0], PARENTS[1:])
    assert all(JOINT_NAMES[t].endswith("_tip") for t in FINGERTIPS)
    # Tagliasacchi et al. 2015 limits: flexion [-0.1, 1.5], abduction per finger.
    assert LOWER[6 + 4 * 1 + 1] == -0.5 and UPPER[6 + 4 * 1 + 1] == 0.4   # index abduction
    assert LOWER[6 + 4 * 4 + 1] == -0.5 and UPPER[6 + 4 * 4 + 1] == 0.3   # pinky abduction
    flex = [6 + 4 * f + k for f in range(5) for k in (0, 2, 3)]
    assert np.all(LOWER[flex] == -0.1) and np.all(UPPER[flex] == 1.5)
    assert np.all(np.isinf(LOWER[:6])) and np.all(np.isinf(UPPER[:6]))


def test_bone_lengths_preserved_in_random_poses():
    sk = HandSkeleton(DEFAULT_BONE_LENGTHS * 1.07)
    j = sk.forward(random_poses(200))
    lengths = np.linalg.norm(j[:, BONES[:, 1]] - j[:, BONES[:, 0]], axis=-1)
    np.testing.assert_allclose(lengths, np.broadcast_to(sk.bone_lengths, lengths.shape), atol=1e-12)


def test_rest_pose_is_a_flat_open_right_hand():
    sk = HandSkeleton()
    rest = sk.rest_joints()
    np.testing.assert_allclose(sk.forward(np.zeros(26)), rest)
    np.testing.assert_allclose(rest[0], 0.0)
    fingers = rest[5:]
    np.testing.assert_allclose(fingers[:, 2], 0.0, atol=1e-12)           # flat in the palm plane
    tips = rest[list(FINGERTIPS)]
    assert np.all(tips[1:, 1] > 0.13)                                      # fingers along +y
    assert np.all(np.diff(tips[1:, 0]) > 0.01)                             # index..pinky from -x to +x
    thumb_dir = rest[4] - rest[1]
    side_angle = np.degrees(np.arctan2(-thumb_dir[0], thumb_dir[1]))
    assert tips[0, 0] < tips[1, 0] and 35 < side_angle < 55                # thumb out to the -x side


def test_global_pose_is_a_rigid_motion_of_the_local_hand():
    sk = HandSkeleton()
    a = random_poses(20, seed=1)
    local = a.copy()
    local[:, :6] = 0
    expected = np.einsum("nij,nkj->nki", Rotation.from_rotvec(a[:, :3]).as_matrix(), sk.forward(local)) + a[:, None, 3:6]
    np.testing.assert_allclose(sk.forward(a), expected, atol=1e-12)


def test_rodrigues_matches_scipy_and_is_exact_at_zero():
    r = np.random.default_rng(2).normal(size=(50, 3))
    r[0] = 0.0
    r[1] = [1e-6, -2e-6, 3e-7]
    np.testing.assert_allclose(rodrigues(r), Rotation.from_rotvec(r).as_matrix(), atol=1e-14)
    r32 = rodrigues(r.astype(np.float32))
    assert r32.dtype == np.float32
    np.testing.assert_allclose(r32, Rotation.from_rotvec(r).as_matrix(), atol=2e-6)


def test_flexion_curls_each_finger_towards_the_palm():
    sk = HandSkeleton()
    rest = sk.rest_joints()
    for f in range(1, 5):
        for k in (0, 2, 3):
            a = np.zeros(26)
            a[6 + 4 * f + k] = 0.8
            tip = sk.forward(a)[FINGERTIPS[f]]
            assert tip[2] < rest[FINGERTIPS[f], 2] - 0.01, (f, k)
    # Abduction turns a finger towards the thumb side (-x).
    a = np.zeros(26)
    a[6 + 4 + 1] = 0.3
    assert sk.forward(a)[8, 0] < rest[8, 0] - 0.01
    # Thumb flexion brings the thumb tip across and in front of the palm, towards the little finger.
    a = np.zeros(26)
    a[6:10] = [1.2, 0.0, 0.6, 0.6]
    tip = sk.forward(a)[4]
    assert tip[0] > rest[9, 0] and tip[2] < -0.02


def test_bone_transforms_carry_rest_joints_to_posed_joints():
    sk = HandSkeleton(DEFAULT_BONE_LENGTHS * 0.93)
    a = random_poses(30, seed=3)
    rot, trans = sk.bone_transforms(a)
    assert rot.shape == (30, 20, 3, 3) and trans.shape == (30, 20, 3)
    rest, posed = sk.rest_joints(), sk.forward(a)
    for end in (0, 1):
        carried = np.einsum("nbij,bj->nbi", rot, rest[BONES[:, end]]) + trans
        np.testing.assert_allclose(carried, posed[:, BONES[:, end]], atol=1e-12)
    np.testing.assert_allclose(rot @ np.swapaxes(rot, -1, -2), np.broadcast_to(np.eye(3), rot.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-12)


def test_numpy_and_torch_agree():
    sk = HandSkeleton()
    a = random_poses(16, seed=4)
    at = torch.from_numpy(a)
    np.testing.assert_allclose(sk.forward(at).numpy(), sk.forward(a), atol=1e-12)
    rn, tn = sk.bone_transforms(a)
    rt, tt = sk.bone_transforms(at)
    np.testing.assert_allclose(rt.numpy(), rn, atol=1e-12)
    np.testing.assert_allclose(tt.numpy(), tn, atol=1e-12)
    np.testing.assert_allclose(sk.clamp(at * 3).numpy(), sk.clamp(a * 3))
    lengths = torch.full((16, 20), 0.03, dtype=torch.float64)
    np.testing.assert_allclose(sk.forward(at, lengths).numpy(), sk.forward(a, np.full((16, 20), 0.03)), atol=1e-12)


def test_torch_gradients_match_finite_differences():
    sk = HandSkeleton()
    a = torch.from_numpy(random_poses(1, seed=5)).requires_grad_(True)
    assert torch.autograd.gradcheck(sk.forward, (a,))
    zero_rot = torch.from_numpy(random_poses(1, seed=6))
    zero_rot[:, :3] = 0.0
    zero_rot.requires_grad_(True)
    assert torch.autograd.gradcheck(sk.forward, (zero_rot,))
    assert torch.autograd.gradcheck(lambda x: sk.bone_transforms(x)[0], (zero_rot,))
    # The same at exactly zero in float32: finite, and equal to the float64 gradient.
    z32 = torch.zeros(26, dtype=torch.float32, requires_grad=True)
    sk.forward(z32).sum().backward()
    z64 = torch.zeros(26, dtype=torch.float64, requires_grad=True)
    sk.forward(z64).sum().backward()
    assert torch.isfinite(z32.grad).all()
    np.testing.assert_allclose(z32.grad.numpy(), z64.grad.numpy(), atol=1e-6)


def test_bone_length_gradient_flows_in_torch():
    sk = HandSkeleton()
    lengths = torch.from_numpy(DEFAULT_BONE_LENGTHS.copy()).requires_grad_(True)
    a = torch.from_numpy(random_poses(3, seed=7))
    assert torch.autograd.gradcheck(lambda L: sk.forward(a, L), (lengths,))


def test_clamp_respects_limits():
    sk = HandSkeleton()
    a = np.random.default_rng(8).normal(scale=3.0, size=(100, 26))
    c = sk.clamp(a)
    assert np.all(sk.within_limits(c))
    assert not np.all(sk.within_limits(a))
    inside = (a >= LOWER) & (a <= UPPER)
    np.testing.assert_array_equal(c[inside], a[inside])
    np.testing.assert_array_equal(c[:, :6], a[:, :6])          # global DOFs are unbounded
    with pytest.raises(ValueError):
        HandSkeleton(np.ones(19))


def test_module_does_not_import_torch():
    code = "import sys, manus_core.skeleton; assert 'torch' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)
