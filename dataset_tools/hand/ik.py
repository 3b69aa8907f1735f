"""Inverse kinematics: the 26-DOF hand skeleton fitted to 3D joints, all frames at once.

    angles, fitted = fit_hand(joints3d, bone_lengths)                       # (T,21,3) -> (T,26), (T,21,3)
    angles, fitted, info = fit_hand(joints3d, confidence=w, return_info=True)

The problem per frame: 26 unknowns (global rotation, wrist position, 5 fingers x 4 angles) against
up to 21 observed joints. What is minimised (docs/annotate.md has the details):

    sum_j w_j huber(|X_j(angles) - Y_j|)  +  limit_weight^2 * sum_i hinge(angle_i outside [lower, upper])^2

w_j = confidence x (tip_weight for the five fingertips); a NaN joint, or a confidence of 0 or NaN,
is missing and does not enter. The solver is Levenberg-Marquardt with the analytic Jacobian:

- Every frame starts from a closed-form estimate: the global pose from the six joints that move
  rigidly with the palm (weighted Kabsch), then each finger's abduction from the plane its bones
  lie in and its flexions from the bone directions in that plane. For exact joints this is the
  answer, and for noisy ones it is close, so every frame can be solved at the same time, with no
  sequential dependence: one batched 26x26 solve per iteration for all frames that are still moving.
- Warm start from the previous frame: a finger whose closed-form start cannot be computed (joints
  missing) starts from the last frame where it could, and frames whose fit ends well above the
  take's typical residual are solved again from the previous frame's solution (all at once), the
  better of the two kept. `init="previous"` is the strictly sequential tracker (each frame from the
  one before), `init="rest"` a cold start (Kabsch pose, straight fingers), and an array (T,26) any
  start the caller has.
- The rotation is updated on the manifold (R <- exp(d) R), so there is no singularity at any pose;
  the rotation vector reported has an angle in [0, pi].
- Limits are a hinge penalty inside the fit (stiff: 1 rad outside costs as much as 1 m of joint
  error), and the result is finally clamped into the limits, which moves a joint by far less than
  a micrometre.

Nothing is invented: a frame with fewer than `min_joints` usable joints is NaN (angles and fitted
joints), and a finger angle that no observed joint depends on is NaN, as are the fitted joints
that depend on it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from manus_core.errors import IKError
from manus_core.rotations import matrix_to_rotvec
from manus_core.skeleton import FINGERTIPS, META_DIRS, N_DOF, REST_FRAMES, HandSkeleton, rodrigues

# Joints that move rigidly with the palm: wrist, thumb CMC, index..pinky MCP.
PALM_JOINTS = np.array([0, 1, 5, 9, 13, 17])
# _FINGER_JOINTS[f, m]: the m-th joint of finger f (m = 0 the base, 3 the tip).
_FINGER_JOINTS = 1 + 4 * np.arange(5)[:, None] + np.arange(4)[None, :]
_FINGER_DOFS = 6 + 4 * np.arange(5)[:, None] + np.arange(4)[None, :]
# Which finger DOF (k: 0 base flexion, 1 abduction, 2 second, 3 third flexion) moves which joint
# (m = 1..3 after the base): DOF k moves joint m when m >= _FIRST_MOVED[k].
_FIRST_MOVED = np.array([1, 1, 2, 3])
_OBSERVES = (np.arange(1, 4)[:, None] >= _FIRST_MOVED[None, :])  # (3 joints, 4 dofs)


@dataclass
class IKInfo:
    """Per-frame diagnostics of fit_hand.

    residual: RMS distance (m) between the fitted and the observed joints over the usable joints
    (NaN for frames not fitted). iterations: LM iterations. converged: the cost stopped changing
    before max_iterations. valid: the frame had at least min_joints usable joints. observed (T,26):
    the DOFs some usable joint depends on (the rest are NaN in the angles).
    """

    residual: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    valid: np.ndarray
    observed: np.ndarray


def _skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices (...,3,3) of vectors (...,3)."""
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([z, -w, y, w, z, -x, -y, x, z], -1).reshape(v.shape[:-1] + (3, 3))


class _HandModel:
    """The skeleton's kinematics in closed form, vectorized over frames and fingers.

    In the hand frame, finger f's base joint sits at META_DIRS[f] * L0 and bone k (k = 1..3) points
    along REST_f @ (-sin a cos c_k, cos a cos c_k, -sin c_k), with a the abduction and c_k the
    cumulative flexion up to that bone: Rz(a) Rx(-c) applied to +y. This is HandSkeleton._chain
    written out, and it gives the Jacobian columns directly (axis x lever arm).
    """

    def __init__(self, skeleton: HandSkeleton) -> None:
        lengths = skeleton.bone_lengths.reshape(5, 4)
        self.base = META_DIRS * lengths[:, :1]                # (5,3) base joints in the hand frame
        self.lengths = lengths[:, 1:]                         # (5,3) moving bones
        self.rest = REST_FRAMES                               # (5,3,3)
        self.lower = skeleton.lower
        self.upper = skeleton.upper
        self.rest_joints = skeleton.rest_joints()

    def local(self, fingers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Hand-frame joints (N,21,3) and flexion axes (N,5,3) for finger angles (N,5,4)."""
        flex = np.cumsum(fingers[..., [0, 2, 3]], axis=-1)     # (N,5,3) cumulative flexion
        sa, ca = np.sin(fingers[..., 1]), np.cos(fingers[..., 1])
        sc, cc = np.sin(flex), np.cos(flex)
        u = np.stack([-sa[..., None] * cc, ca[..., None] * cc, -sc], -1)   # (N,5,3 bones,3)
        d = np.einsum("fij,nfkj->nfki", self.rest, u) * self.lengths[..., None]
        n = fingers.shape[0]
        P = np.zeros((n, 21, 3))
        P[:, _FINGER_JOINTS[:, 0]] = self.base
        P[:, _FINGER_JOINTS[:, 1:]] = self.base[:, None, :] + np.cumsum(d, axis=2)
        axis = np.einsum("fij,nfj->nfi", self.rest, np.stack([ca, sa, np.zeros_like(sa)], -1))
        return P, axis

    def forward(self, R: np.ndarray, t: np.ndarray, fingers: np.ndarray) -> np.ndarray:
        P, _ = self.local(fingers)
        return np.einsum("nij,nkj->nki", R, P) + t[:, None, :]

    def jacobian(self, R: np.ndarray, t: np.ndarray, fingers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World joints X (N,21,3) and dX/dparams (N,21,26,3).

        Parameters: a world-frame rotation increment (R <- exp(d) R), the wrist translation and
        the 20 finger angles in DOF order.
        """
        P, axis = self.local(fingers)
        X = np.einsum("nij,nkj->nki", R, P) + t[:, None, :]
        n = len(X)
        J = np.zeros((n, 21, 26, 3))
        # d(R p + t)/d(rotation increment) = -[R p]_x; stored transposed (param, xyz): [R p]_x.
        J[:, :, 0:3, :] = _skew(X - t[:, None, :])
        J[:, :, 3:6, :] = np.eye(3)
        # Finger DOFs in the hand frame: flexion turns about -axis, abduction about REST_f z, each
        # at its own joint (base for flexion 1 and abduction, then the second and third joints).
        joints = P[:, _FINGER_JOINTS]                                   # (N,5,4,3)
        pivots = joints[:, :, [0, 0, 1, 2]]                             # (N,5,4 dofs,3)
        lever = joints[:, :, 1:, None, :] - pivots[:, :, None, :, :]    # (N,5,3 joints,4 dofs,3)
        axes = np.broadcast_to(axis[:, :, None, :], (n, 5, 4, 3)).copy()
        axes[:, :, 1] = self.rest[None, :, :, 2]
        sign = np.array([-1.0, 1.0, -1.0, -1.0])[:, None]
        dP = np.cross(axes[:, :, None] * sign, lever) * _OBSERVES[None, None, :, :, None]
        dX = np.einsum("nij,nfmkj->nfmki", R, dP)
        J[:, _FINGER_JOINTS[:, 1:, None], _FINGER_DOFS[:, None, :], :] = dX
        return X, J

    def initial_pose(self, Y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Closed-form start: (R (N,3,3), t (N,3), fingers (N,5,4) with NaN where unknown, ok (N,))."""
        src = self.rest_joints[PALM_JOINTS]
        dst = np.nan_to_num(Y[:, PALM_JOINTS])
        wp = np.where(w[:, PALM_JOINTS] > 0, 1.0, 0.0)
        ok = wp.sum(1) >= 3
        ws = np.maximum(wp.sum(1, keepdims=True), 1e-12)
        cs = (wp @ src) / ws
        cd = np.einsum("nj,njk->nk", wp, dst) / ws
        H = np.einsum("nj,nja,njb->nab", wp, src[None] - cs[:, None], dst - cd[:, None])
        U, _, Vt = np.linalg.svd(H)
        det = np.sign(np.linalg.det(np.swapaxes(Vt, 1, 2) @ np.swapaxes(U, 1, 2)))
        D = np.zeros((len(Y), 3, 3))
        D[:, 0, 0] = D[:, 1, 1] = 1.0
        D[:, 2, 2] = np.where(det == 0, 1.0, det)
        R = np.swapaxes(Vt, 1, 2) @ D @ np.swapaxes(U, 1, 2)
        t = cd - np.einsum("nij,nj->ni", R, cs)
        # Fingers: bone directions in each finger's rest frame. All of a finger's bones lie in the
        # plane spanned by its forward direction f = (-sin a, cos a, 0) and z, so a comes from the
        # principal direction of their xy components, and each cumulative flexion from atan2.
        Q = np.einsum("nji,nkj->nki", R, Y - t[:, None, :])   # R^T (Y - t)
        Q = np.where((w > 0)[..., None], Q, np.nan)
        fj = Q[:, _FINGER_JOINTS]                              # (N,5,4,3)
        bones = np.einsum("fji,nfkj->nfki", self.rest, np.diff(fj, axis=2))   # in REST_f coords
        have = np.isfinite(bones).all(-1)
        b = np.where(have[..., None], bones, 0.0)
        mxx, myy, mxy = (b[..., 0] ** 2).sum(-1), (b[..., 1] ** 2).sum(-1), (b[..., 0] * b[..., 1]).sum(-1)
        phi = 0.5 * np.arctan2(2 * mxy, mxx - myy)
        abd = np.mod(phi, np.pi) - np.pi / 2      # phi - pi/2, taken into [-pi/2, pi/2)
        abd = np.where(have.any(-1), abd, np.nan)
        forward = -np.sin(abd)[..., None] * bones[..., 0] + np.cos(abd)[..., None] * bones[..., 1]
        cum = np.arctan2(-bones[..., 2], forward)                             # (N,5,3), NaN if missing
        # The cumulative flexion passes pi in a fist; each joint's own flexion is well inside (-pi, pi].
        steps = np.angle(np.exp(1j * np.diff(cum, axis=-1)))
        fingers = np.stack([cum[..., 0], abd, steps[..., 0], steps[..., 1]], -1)
        return R, t, fingers, ok


def _fill_forward(x: np.ndarray, known: np.ndarray) -> np.ndarray:
    """x (T,...) with rows where `known` (T,...) is False taken from the last known row before
    them (from the first known row after them at the start); NaN where never known."""
    T = len(x)
    idx = np.where(known, np.arange(T).reshape((T,) + (1,) * (x.ndim - 1)), -1)
    last = np.maximum.accumulate(idx, axis=0)
    first = np.flip(np.minimum.accumulate(np.flip(np.where(known, idx, T), 0), axis=0), 0)
    src = np.where(last >= 0, last, first)
    filled = np.take_along_axis(x, np.clip(src, 0, T - 1), axis=0)
    return np.where(src < T, filled, np.nan)


class _Problem:
    """The weighted, robust least-squares problem of a batch of frames."""

    def __init__(self, model: _HandModel, Y: np.ndarray, w: np.ndarray, limit_weight: float, huber_m: float):
        self.model, self.Y, self.w = model, np.nan_to_num(Y), w
        self.limit_weight, self.huber = limit_weight, huber_m
        self.lo, self.hi = model.lower[6:].reshape(5, 4), model.upper[6:].reshape(5, 4)

    def subset(self, rows) -> "_Problem":
        return _Problem(self.model, self.Y[rows], self.w[rows], self.limit_weight, self.huber)

    def cost(self, X: np.ndarray, fingers: np.ndarray, idx: np.ndarray) -> np.ndarray:
        dist = np.linalg.norm(X - self.Y[idx], axis=-1)
        rho = np.where(dist <= self.huber, dist ** 2, self.huber * (2 * dist - self.huber))
        over = fingers - np.clip(fingers, self.lo, self.hi)
        return (self.w[idx] * rho).sum(1) + self.limit_weight ** 2 * (over ** 2).sum((1, 2))

    def normal_equations(self, X: np.ndarray, J: np.ndarray, fingers: np.ndarray,
                         idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gauss-Newton A (n,26,26) and gradient g (n,26), Huber by IRLS weights at X."""
        e = X - self.Y[idx]
        dist = np.linalg.norm(e, axis=-1)
        irls = np.minimum(1.0, self.huber / np.maximum(dist, 1e-300))
        ww = self.w[idx] * irls
        Jw = J * np.sqrt(ww)[:, :, None, None]
        Jf = Jw.transpose(0, 2, 1, 3).reshape(len(idx), 26, 63)
        A = Jf @ Jf.transpose(0, 2, 1)
        g = np.einsum("njpa,nja->np", J, e * ww[..., None])
        over = (fingers - np.clip(fingers, self.lo, self.hi)).reshape(len(idx), 20)
        active = (over != 0) * self.limit_weight ** 2
        A[:, np.arange(6, 26), np.arange(6, 26)] += active
        g[:, 6:] += active * over
        return A, g


def _solve(problem: _Problem, R: np.ndarray, t: np.ndarray, fingers: np.ndarray, max_iterations: int,
           tolerance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on every frame of the batch at once; frames leave the batch as they
    converge. Returns R, t, fingers, cost, iterations, converged."""
    model = problem.model
    n = len(R)
    R, t, fingers = R.copy(), t.copy(), fingers.copy()
    iterations = np.zeros(n, np.int64)
    converged = np.zeros(n, bool)
    lam = np.full(n, 1e-3)
    active = np.arange(n)
    X, J = model.jacobian(R, t, fingers)
    cost = problem.cost(X, fingers, active)
    A, g = problem.normal_equations(X, J, fingers, active)
    diag = np.arange(26)
    for _ in range(max_iterations):
        if not len(active):
            break
        # Marquardt's scaling, plus a floor so that a DOF no joint depends on stays where it is.
        damped = A.copy()
        damped[:, diag, diag] += lam[active, None] * (A[:, diag, diag] + 1e-9)
        step = -np.linalg.solve(damped, g[..., None])[..., 0]
        # The Gauss-Newton model of the current point does not know where the hinge switches on
        # or off. A DOF whose step would leave the limits meets the hinge there, and one whose step
        # would come back inside through a limit stops on it (the data pushed it out): such frames
        # solve again with those DOFs tied to the limit, with the hinge's stiffness or far stiffer.
        # Without this LM crawls along the limits by rejected steps, and most poses touch one.
        cur = fingers[active].reshape(-1, 20)
        pred = cur + step[:, 6:]
        lo, hi = problem.lo.reshape(20), problem.hi.reshape(20)
        leaving = ((pred > hi) & (cur <= hi)) | ((pred < lo) & (cur >= lo))
        returning = ((pred < hi) & (cur > hi)) | ((pred > lo) & (cur < lo))
        bound = np.where((pred > hi) | (cur > hi), hi, lo)
        rows = np.flatnonzero((leaving | returning).any(1))
        if len(rows):
            k2 = problem.limit_weight ** 2 * (leaving[rows] + 1e6 * returning[rows])
            damped[rows[:, None], 6 + np.arange(20), 6 + np.arange(20)] += k2
            rhs = g[rows].copy()
            rhs[:, 6:] += k2 * (cur[rows] - bound[rows])
            step[rows] = -np.linalg.solve(damped[rows], rhs[..., None])[..., 0]
        R_new = rodrigues(step[:, :3]) @ R[active]
        t_new = t[active] + step[:, 3:6]
        f_new = fingers[active] + step[:, 6:].reshape(-1, 5, 4)
        X_new, J_new = model.jacobian(R_new, t_new, f_new)
        cost_new = problem.cost(X_new, f_new, active)
        iterations[active] += 1
        better = cost_new < cost
        acc = active[better]
        R[acc], t[acc], fingers[acc] = R_new[better], t_new[better], f_new[better]
        A_new, g_new = problem.normal_equations(X_new[better], J_new[better], f_new[better], acc)
        A[better], g[better] = A_new, g_new
        decrease = cost - np.where(better, cost_new, cost)
        cost = np.where(better, cost_new, cost)
        lam[acc] = np.maximum(lam[acc] / 3.0, 1e-9)
        lam[active[~better]] *= 4.0
        small_step = np.abs(step).max(1) < 1e-7   # 0.1 um, 0.1 urad: far below any noise
        done = (better & (decrease <= tolerance * (cost + 1e-12))) | small_step | (lam[active] > 1e8)
        converged[active[done]] = True
        keep = ~done
        active, A, g, cost = active[keep], A[keep], g[keep], cost[keep]
    final_cost = problem.cost(model.forward(R, t, fingers), fingers, np.arange(n))
    return R, t, fingers, final_cost, iterations, converged


def _weights(joints3d: np.ndarray, confidence: Any, tip_weight: float) -> np.ndarray:
    w = np.ones(joints3d.shape[:2]) if confidence is None else np.array(confidence, dtype=np.float64)
    if w.shape != joints3d.shape[:2]:
        raise IKError(f"fit_hand: confidence has shape {w.shape}, expected {joints3d.shape[:2]}")
    w = np.where(np.isfinite(w) & np.isfinite(joints3d).all(-1), w, 0.0)
    if (w < 0).any():
        raise IKError("fit_hand: confidence must be >= 0")
    w[:, list(FINGERTIPS)] *= tip_weight
    return w


def fit_hand(joints3d: np.ndarray, bone_lengths: np.ndarray | None = None, *, confidence: np.ndarray | None = None,
             skeleton: HandSkeleton | None = None, init: str | np.ndarray = "closed-form",
             tip_weight: float = 2.0, limit_weight: float = 1.0, huber_m: float = 0.005,
             max_iterations: int = 30, tolerance: float = 1e-6, min_joints: int = 6,
             retry_factor: float = 3.0, return_info: bool = False):
    """Fit the 26-DOF hand to 3D joints (T,21,3) (metres, MediaPipe order; NaN = missing).

    bone_lengths: the subject's 20 bones (default: the skeleton's); skeleton: a HandSkeleton whose
    joint limits (and bone lengths, unless given) are used. confidence (T,21): per-joint weights,
    0 or NaN = missing. init: "closed-form" (default, every frame at once, see the module doc),
    "previous" (sequential warm start from the previous frame), "rest" (cold start) or an array
    (T,26) of starting angles (NaN rows: closed form). tip_weight multiplies the fingertips'
    weights; limit_weight is the hinge stiffness (m of joint error per rad outside the limits);
    huber_m the distance (m) beyond which a joint's pull stops growing (outlier joints).
    retry_factor: frames whose residual exceeds this times the median residual (and 1 mm) are
    solved again from the previous frame's solution (closed-form init only; 0 turns it off).

    Returns angles (T,26) and fitted joints (T,21,3), NaN where not observable (see the module
    doc); with return_info=True also an IKInfo with the per-frame residual.
    """
    Y = np.array(joints3d, dtype=np.float64)
    if Y.ndim == 2:
        Y = Y[None]
    if Y.ndim != 3 or Y.shape[1:] != (21, 3):
        raise IKError(f"fit_hand: joints3d must be (T, 21, 3), got shape {np.shape(joints3d)}")
    skeleton = skeleton or HandSkeleton()
    if bone_lengths is not None:
        skeleton = HandSkeleton(bone_lengths, skeleton.lower, skeleton.upper)
    model = _HandModel(skeleton)
    w = _weights(Y, confidence, tip_weight)
    n_t = len(Y)
    valid = (w > 0).sum(1) >= min_joints
    frames = np.flatnonzero(valid)
    if not len(frames):
        empty = np.full((n_t, N_DOF), np.nan), np.full((n_t, 21, 3), np.nan)
        if not return_info:
            return empty
        return empty + (IKInfo(np.full(n_t, np.nan), np.zeros(n_t, np.int64), np.zeros(n_t, bool), valid,
                               np.zeros((n_t, N_DOF), bool)),)
    R0, t0, f0, pose_ok = model.initial_pose(Y[frames], w[frames])
    # A start that cannot be computed (palm joints or a finger's joints missing) comes from the
    # nearest frame where it could be: the previous one, or the next at the start of the take.
    R0 = _fill_forward(R0, np.broadcast_to(pose_ok[:, None, None], R0.shape))
    t0 = _fill_forward(t0, np.broadcast_to(pose_ok[:, None], t0.shape))
    f0 = _fill_forward(f0, np.isfinite(f0))
    if len(frames) and not pose_ok.any():
        # No frame shows three palm joints: centre the rest hand on the joints that are there.
        R0 = np.broadcast_to(np.eye(3), R0.shape).copy()
        t0 = np.nansum(Y[frames] * (w[frames] > 0)[..., None], 1) / (w[frames] > 0).sum(1)[:, None]
    f0 = np.nan_to_num(f0)
    if isinstance(init, str) and init == "rest":
        f0 = np.zeros_like(f0)
    elif not isinstance(init, str):
        start = np.asarray(init, dtype=np.float64)
        if start.shape != (n_t, N_DOF):
            raise IKError(f"fit_hand: init array has shape {start.shape}, expected ({n_t}, 26)")
        given = np.isfinite(start[frames]).all(1)
        R0[given] = rodrigues(start[frames][given, :3])
        t0[given] = start[frames][given, 3:6]
        f0[given] = start[frames][given, 6:].reshape(-1, 5, 4)
    elif init not in ("closed-form", "previous"):
        raise IKError(f"fit_hand: init = {init!r}; use 'closed-form', 'previous', 'rest' or an array (T, 26)")
    f0 = skeleton.clamp(np.concatenate([np.zeros((len(frames), 6)), f0.reshape(-1, 20)], 1))[:, 6:].reshape(-1, 5, 4)

    problem = _Problem(model, Y[frames], w[frames], limit_weight, huber_m)
    if isinstance(init, str) and init == "previous":
        R, t, fingers, cost, iters, conv = _solve_sequential(problem, R0, t0, f0, frames, max_iterations, tolerance)
    else:
        R, t, fingers, cost, iters, conv = _solve_blocks(problem, R0, t0, f0, max_iterations, tolerance)
        if retry_factor > 0 and isinstance(init, str) and len(frames) > 1:
            _retry_from_previous(problem, R, t, fingers, cost, iters, conv, frames, retry_factor,
                                 max_iterations, tolerance)

    fingers = skeleton.clamp(np.concatenate([np.zeros((len(frames), 6)), fingers.reshape(-1, 20)], 1))[:, 6:]
    angles = np.full((n_t, N_DOF), np.nan)
    angles[frames, :3] = matrix_to_rotvec(R)
    angles[frames, 3:6] = t
    angles[frames, 6:] = fingers
    used = w > 0
    finger_seen = used[:, _FINGER_JOINTS[:, 1:]]                          # (T,5,3)
    observed = np.zeros((n_t, N_DOF), bool)
    observed[:, :6] = valid[:, None]
    observed[:, 6:] = ((finger_seen[..., :, None] & _OBSERVES).any(2) & valid[:, None, None]).reshape(n_t, 20)
    angles[~observed] = np.nan
    fitted = np.full((n_t, 21, 3), np.nan)
    fitted[frames] = model.forward(R, t, angles[frames, 6:].reshape(-1, 5, 4))
    if not return_info:
        return angles, fitted
    d2 = np.where(used, ((fitted - np.nan_to_num(Y)) ** 2).sum(-1), 0.0)
    with np.errstate(invalid="ignore"):
        residual = np.sqrt(d2.sum(1) / used.sum(1))
    residual[~valid] = np.nan
    iterations = np.zeros(n_t, np.int64)
    converged = np.zeros(n_t, bool)
    iterations[frames], converged[frames] = iters, conv
    return angles, fitted, IKInfo(residual, iterations, converged, valid, observed)


_BLOCK = 256  # frames per batched solve: bounds the (frames, 21, 26, 3) Jacobians to ~25 MB


def _solve_blocks(problem: _Problem, R0, t0, f0, max_iterations, tolerance):
    """_solve over blocks of frames (all frames of a block at once), results concatenated."""
    parts = [_solve(problem.subset(slice(s, s + _BLOCK)), R0[s:s + _BLOCK], t0[s:s + _BLOCK], f0[s:s + _BLOCK],
                    max_iterations, tolerance) for s in range(0, len(R0), _BLOCK)]
    return tuple(np.concatenate(p) for p in zip(*parts))


def _solve_sequential(problem: _Problem, R0, t0, f0, frames, max_iterations, tolerance):
    """Each frame from the previous frame's solution (the first from its closed-form start)."""
    n = len(frames)
    R, t, fingers = R0.copy(), t0.copy(), f0.copy()
    cost = np.zeros(n)
    iters = np.zeros(n, np.int64)
    conv = np.zeros(n, bool)
    for i in range(n):
        sub = problem.subset(slice(i, i + 1))
        start = (R0[i:i + 1], t0[i:i + 1], f0[i:i + 1]) if i == 0 else (R[i - 1:i], t[i - 1:i], fingers[i - 1:i])
        out = _solve(sub, *start, max_iterations, tolerance)
        R[i], t[i], fingers[i], cost[i], iters[i], conv[i] = (o[0] for o in out)
    return R, t, fingers, cost, iters, conv


def _retry_from_previous(problem, R, t, fingers, cost, iters, conv, frames, factor, max_iterations, tolerance):
    """Frames that ended far above the typical cost (a local minimum of the closed-form start)
    are solved again from the previous frame's solution; the better result is kept (in place)."""
    n_used = np.maximum((problem.w > 0).sum(1), 1)
    per_joint = cost / n_used
    limit = max(factor ** 2 * float(np.median(per_joint)), 1e-6)
    retry = np.flatnonzero(per_joint > limit)
    # Only where the previous solved frame is the frame just before (a jump in the take is no warm start).
    retry = retry[(retry > 0) & (frames[retry] - frames[np.maximum(retry - 1, 0)] == 1)]
    if not len(retry):
        return
    prev = retry - 1
    sub = problem.subset(retry)
    R2, t2, f2, c2, it2, cv2 = _solve_blocks(sub, R[prev], t[prev], fingers[prev], max_iterations, tolerance)
    better = c2 < cost[retry]
    keep = retry[better]
    R[keep], t[keep], fingers[keep], cost[keep], conv[keep] = R2[better], t2[better], f2[better], c2[better], cv2[better]
    iters[retry] += it2


def unwrap_rotations(angles: np.ndarray) -> np.ndarray:
    """Angles (T,26) whose rotation vectors (columns 0:3) are continuous in time.

    A rotation vector r and r - 2 pi r/|r| are the same rotation; near a half turn the reported
    vector can flip between them from one frame to the next, which a per-channel filter would
    smear. The rotations become unit quaternions whose signs are chained so that neighbours agree
    (q and -q are the same rotation), and each is turned back into a vector of angle
    2 atan2(|v|, w), which then varies continuously (NaN frames are skipped). wrap_rotations
    undoes it after filtering.
    """
    out = np.array(angles, dtype=np.float64)
    good = np.flatnonzero(np.isfinite(out[:, :3]).all(1))
    if len(good) < 2:
        return out
    q = Rotation.from_rotvec(out[good, :3]).as_quat()          # (x, y, z, w)
    flips = np.sign(np.einsum("ij,ij->i", q[1:], q[:-1]))
    flips[flips == 0] = 1.0
    q *= np.concatenate([[1.0], np.cumprod(flips)])[:, None]
    v = q[:, :3]
    norm = np.linalg.norm(v, axis=1, keepdims=True)
    angle = 2 * np.arctan2(norm, q[:, 3:])
    out[good, :3] = np.where(norm > 1e-12, v / np.maximum(norm, 1e-300) * angle, 2 * v)
    return out


def wrap_rotations(angles: np.ndarray) -> np.ndarray:
    """Angles (T,26) with every rotation vector brought to an angle in [0, pi] (NaN kept)."""
    out = np.array(angles, dtype=np.float64)
    good = np.isfinite(out[:, :3]).all(1)
    out[good, :3] = matrix_to_rotvec(rodrigues(out[good, :3]))
    return out
