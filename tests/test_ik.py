"""Inverse kinematics of the 26-DOF hand: exact recovery, limits, warm start, missing joints, robustness."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dataset_tools.hand.ik import _HandModel, fit_hand, unwrap_rotations, wrap_rotations
from manus_core.errors import IKError
from manus_core.skeleton import FINGERTIPS, LOWER, UPPER, HandSkeleton, rodrigues
from rig.sim.hand import make_hand
from rig.sim.motion import make_motion
from rig.sim.objects import make_object

SUBJECT = make_hand("s03").skeleton.bone_lengths   # not the default skeleton: bone lengths must be used


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = np.zeros((n, 26))
    a[:, :3] = Rotation.random(n, random_state=seed).as_rotvec()
    a[:, 3:6] = rng.uniform(-0.3, 0.3, (n, 3))
    a[:, 6:] = rng.uniform(LOWER[6:], UPPER[6:], (n, 20))
    return a


def rotation_error(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Geodesic angle (rad) between the global rotations of two pose arrays."""
    rel = np.swapaxes(rodrigues(a[:, :3]), 1, 2) @ rodrigues(b[:, :3])
    return Rotation.from_matrix(rel).magnitude()


def test_analytic_jacobian_matches_finite_differences():
    a = random_poses(20, seed=3)
    model = _HandModel(HandSkeleton(SUBJECT))
    R, t, f = rodrigues(a[:, :3]), a[:, 3:6], a[:, 6:].reshape(-1, 5, 4)
    X, J = model.jacobian(R, t, f)
    np.testing.assert_allclose(X, HandSkeleton(SUBJECT).forward(a), atol=1e-14)
    eps = 1e-7
    for p in range(26):
        d = np.zeros(26)
        d[p] = eps
        Xp = model.forward(rodrigues(np.tile(d[:3], (20, 1))) @ R, t + d[3:6], f + d[6:].reshape(5, 4))
        np.testing.assert_allclose(J[:, :, p], (Xp - X) / eps, atol=1e-6)


@pytest.mark.parametrize("init", ["closed-form", "rest"])
def test_recovers_random_in_limit_poses_from_exact_joints(init):
    truth = random_poses(300, seed=1)
    joints = HandSkeleton(SUBJECT).forward(truth)
    angles, fitted, info = fit_hand(joints, SUBJECT, init=init, return_info=True)
    assert info.valid.all() and info.converged.all()
    np.testing.assert_allclose(fitted, joints, atol=1e-9)
    if init == "closed-form":
        # The closed-form start is the answer: every finger angle to 1e-9 rad.
        np.testing.assert_allclose(angles[:, 6:], truth[:, 6:], atol=1e-9)
        assert rotation_error(angles, truth).max() < 1e-9
        assert info.iterations.max() <= 2
    else:
        # From straight fingers some random poses (fists seen from any side) end in another local
        # minimum; most are recovered exactly.
        good = np.abs(angles[:, 6:] - truth[:, 6:]).max(1) < 1e-6
        assert good.mean() > 0.9
    np.testing.assert_allclose(angles[:, 3:6], truth[:, 3:6], atol=1e-9)
    assert np.linalg.norm(angles[:, :3], axis=1).max() <= np.pi + 1e-12


def test_respects_joint_limits():
    truth = random_poses(100, seed=2)
    beyond = truth.copy()
    flex = [6 + 4 * f + k for f in range(5) for k in (0, 2, 3)]
    beyond[:50, flex] = 1.9                      # fists curled past the 1.5 rad limit
    beyond[50:, [10, 12, 13]] = 0.2              # the index bent a little (bent more it could trade
    beyond[50:, 11] = -0.8                       # abduction for flexion), abducted far past -0.5
    angles, fitted = fit_hand(HandSkeleton(SUBJECT).forward(beyond), SUBJECT)
    sk = HandSkeleton(SUBJECT)
    assert sk.within_limits(angles).all()
    # The DOFs driven past a limit end on it, or next to it where bending a neighbour a little
    # less brings the finger closer to the curled-up joints.
    np.testing.assert_allclose(angles[:50, flex], 1.5, atol=0.01)
    np.testing.assert_allclose(angles[50:, 11], LOWER[11], atol=0.01)
    np.testing.assert_allclose(fitted, sk.forward(angles), atol=1e-12)


def hand_sequence(n: int = 120, fps: float = 120.0) -> np.ndarray:
    """The closing of a 3-second grasp: fingers curling onto the object, at 120 frames/s."""
    hand = make_hand("s03")
    motion = make_motion("grasp", hand, make_object("box"), 3.0, seed=1)
    return motion.hand_angles(0.7 + np.arange(n) / fps)


def test_warm_start_needs_fewer_iterations_than_a_cold_start():
    truth = hand_sequence()
    rng = np.random.default_rng(0)
    joints = HandSkeleton(SUBJECT).forward(truth) + rng.normal(scale=0.5e-3, size=(len(truth), 21, 3))
    warm = fit_hand(joints, SUBJECT, init="previous", return_info=True)
    cold = fit_hand(joints, SUBJECT, init="rest", return_info=True)
    batch = fit_hand(joints, SUBJECT, return_info=True)
    assert warm[2].iterations.mean() < 0.8 * cold[2].iterations.mean()
    assert batch[2].iterations.mean() <= warm[2].iterations.mean()
    # Same optimum whichever start: the fitted joints agree to a micrometre.
    np.testing.assert_allclose(warm[1], batch[1], atol=1e-6)
    np.testing.assert_allclose(cold[1], batch[1], atol=1e-6)
    # And it is the right one: with 0.5 mm joint noise the joints come back within 0.6 mm (mean).
    assert np.linalg.norm(batch[1] - HandSkeleton(SUBJECT).forward(truth), axis=-1).mean() < 0.6e-3


def test_missing_joints_are_ignored_and_unobservable_angles_are_nan():
    truth = random_poses(6, seed=4)
    joints = HandSkeleton(SUBJECT).forward(truth)
    joints[0, 8] = np.nan                     # index tip: its DIP flexion cannot be seen
    joints[1, [17, 18, 19, 20]] = np.nan      # the whole pinky: its 4 DOFs cannot be seen
    joints[2, [0, 1, 5, 9, 13]] = np.nan      # palm joints: the pose comes from the fingers
    joints[3, :16] = np.nan                   # 5 joints left: below min_joints = 6
    confidence = np.ones((6, 21))
    confidence[4, 12] = 0.0                   # middle tip given zero confidence: missing as well
    joints[5] = np.nan                        # nothing at all
    angles, fitted, info = fit_hand(joints, SUBJECT, confidence=confidence, return_info=True)
    dip = 6 + 4 * 1 + 3
    assert np.isnan(angles[0, dip]) and np.isnan(fitted[0, 8]).all()
    keep = np.setdiff1d(np.arange(26), [dip])
    np.testing.assert_allclose(angles[0, keep][6:], truth[0, keep][6:], atol=1e-8)
    assert np.isnan(angles[1, 22:26]).all() and np.isnan(fitted[1, 18:21]).all()
    np.testing.assert_allclose(fitted[1, :18], HandSkeleton(SUBJECT).forward(truth[1])[:18], atol=1e-9)
    np.testing.assert_allclose(fitted[2], HandSkeleton(SUBJECT).forward(truth[2]), atol=1e-8)
    assert not info.valid[3] and np.isnan(angles[3]).all() and np.isnan(fitted[3]).all()
    assert np.isnan(angles[4, 6 + 4 * 2 + 3]) and np.isfinite(angles[4, 6 + 4 * 2 + 2])
    assert not info.valid[5] and np.isnan(info.residual[5]) and np.isnan(angles[5]).all()
    everything_missing = fit_hand(np.full((3, 21, 3), np.nan), return_info=True)
    assert np.isnan(everything_missing[0]).all() and not everything_missing[2].valid.any()


def test_outlier_joint_barely_moves_the_fit():
    truth = random_poses(40, seed=5)
    joints = HandSkeleton(SUBJECT).forward(truth)
    noisy = joints.copy()
    noisy[:, 16] += np.array([0.05, -0.03, 0.04])      # ring tip triangulated 7 cm off in every frame
    others = np.setdiff1d(np.arange(21), [13, 14, 15, 16])
    robust = np.linalg.norm(fit_hand(noisy, SUBJECT)[1][:, others] - joints[:, others], axis=-1)
    plain = np.linalg.norm(fit_hand(noisy, SUBJECT, huber_m=np.inf)[1][:, others] - joints[:, others], axis=-1)
    # The Huber loss caps the outlier's pull: the rest of the hand moves 0.59 mm on average (3.5 mm
    # at worst), a seventh of what plain least squares gives (4.1 mm, 18 mm at worst).
    assert robust.mean() < 0.8e-3 and robust.max() < 5e-3
    assert robust.mean() < plain.mean() / 5 and robust.max() < plain.max() / 4


def test_tip_weight_and_confidence_shift_the_compromise():
    truth = random_poses(20, seed=6)
    joints = HandSkeleton(SUBJECT).forward(truth)
    rng = np.random.default_rng(1)
    noisy = joints + rng.normal(scale=2e-3, size=joints.shape)
    tips = list(FINGERTIPS)
    plain = fit_hand(noisy, SUBJECT, tip_weight=1.0)[1]
    heavy = fit_hand(noisy, SUBJECT, tip_weight=10.0)[1]
    # Heavier tips: the fit follows the (noisy) tips more closely than with equal weights.
    assert np.linalg.norm(heavy[:, tips] - noisy[:, tips], axis=-1).mean() < \
        np.linalg.norm(plain[:, tips] - noisy[:, tips], axis=-1).mean()


def test_rotation_unwrap_makes_a_half_turn_continuous_and_wrap_undoes_it():
    axis = np.array([0.0, 0.6, 0.8])
    theta = np.linspace(np.pi - 0.3, np.pi + 0.3, 31)
    angles = np.zeros((31, 26))
    angles[:, :3] = Rotation.from_rotvec(theta[:, None] * axis).as_rotvec()   # jumps at pi
    assert np.abs(np.diff(angles[:, :3], axis=0)).max() > 1.0
    angles[10] = np.nan
    unwrapped = unwrap_rotations(angles)
    steps = np.abs(np.diff(np.delete(unwrapped[:, :3], 10, axis=0), axis=0)).max()
    assert steps < 0.05
    back = wrap_rotations(unwrapped)
    assert np.isnan(back[10]).all()
    ok = np.isfinite(angles[:, 0])
    assert rotation_error(back[ok], angles[ok]).max() < 1e-12
    assert np.linalg.norm(back[ok, :3], axis=1).max() <= np.pi + 1e-12


def test_bad_input_raises_ik_error():
    with pytest.raises(IKError, match=r"\(T, 21, 3\)"):
        fit_hand(np.zeros((4, 20, 3)))
    with pytest.raises(IKError, match="confidence"):
        fit_hand(np.zeros((4, 21, 3)), confidence=np.ones((4, 20)))
    with pytest.raises(IKError, match="init"):
        fit_hand(HandSkeleton().forward(np.zeros((2, 26))), init="sideways")
    with pytest.raises(ValueError, match="bone_lengths"):
        fit_hand(np.zeros((1, 21, 3)), bone_lengths=np.ones(19))
