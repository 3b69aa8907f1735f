"""Extrinsics of a camera rig, and one bundle adjustment for every kind of target.

Two sessions are handled:
- Tags on the walls (MANUS cube): every camera is static and sees tags whose corners are known in
  the world frame (tags.json). Each camera's pose comes from PnP with a RANSAC over whole tags;
  then one bundle adjustment refines all cameras together, and optionally the tags themselves (a
  printed layout measured to a few millimetres) under a prior to the layout.
- A board waved through the volume (caliscope-style): in each synchronized frame the board is
  seen by some cameras. Board poses from PnP give camera-to-camera transforms, chained over a
  maximum spanning tree of the cameras that see the board together; then one bundle adjustment
  of every camera's pose and intrinsics and every frame's board pose.

The bundle adjuster (`bundle_adjust`) is a Levenberg-Marquardt with a robust soft-L1 loss and a
sparse Jacobian: each residual depends on one camera and one rigid object (a board pose, a tag,
or the fixed world), so finite differences need 21 vectorized evaluations per iteration whatever
the number of cameras, and the object poses are eliminated (Schur complement) before each solve.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from manus_core.cameras import CameraRig
from .boards import Board, CalibrationError, TagLayout
from .detect import Detection
from .intrinsics import Intrinsics, IntrinsicsError, calibrate_intrinsics

N_INTRINSICS = 9  # fx, fy, cx, cy, k1, k2, p1, p2, k3
MIN_TAG_POINTS = 8  # two tags: PnP with a margin against one mis-decoded tag


class ExtrinsicsError(CalibrationError):
    """Cameras that cannot be placed; the message names them and says why."""


# --- rotations --------------------------------------------------------------------------------

def rotvec_to_matrix(r: np.ndarray) -> np.ndarray:
    """Rodrigues vectors (...,3) to rotation matrices (...,3,3)."""
    from scipy.spatial.transform import Rotation

    r = np.asarray(r, np.float64)
    return Rotation.from_rotvec(r.reshape(-1, 3)).as_matrix().reshape(r.shape[:-1] + (3, 3))


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, np.float64)
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(R.shape[:-2] + (3,))


def mean_rotation(Rs: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of rotations (N,3,3) after dropping those far from the median estimate."""
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_matrix(Rs)
    first = rot.mean()
    angle = (first.inv() * rot).magnitude()
    keep = angle <= max(3 * np.median(angle), np.deg2rad(1.0))
    return rot[keep].mean().as_matrix()


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """Angle of Ra^T Rb in degrees, batched."""
    cos = (np.einsum("...ji,...ji->...", Ra, Rb) - 1) / 2
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


# --- projection -------------------------------------------------------------------------------

def project_points(Xc: np.ndarray, intr: np.ndarray) -> np.ndarray:
    """Camera-frame points (M,3) with per-point intrinsics (M,9) to distorted pixels (M,2)."""
    z = Xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = Xc[:, 0] / z, Xc[:, 1] / z
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = intr.T
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([fx * xd + cx, fy * yd + cy], axis=1)


def pack_intrinsics(K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    K = np.asarray(K)
    return np.concatenate([K[..., [0, 1, 0, 1], [0, 1, 2, 2]], np.asarray(dist)[..., :5]], axis=-1)


def unpack_intrinsics(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 0], K[..., 1, 1], K[..., 0, 2], K[..., 1, 2] = v[..., 0], v[..., 1], v[..., 2], v[..., 3]
    K[..., 2, 2] = 1
    return K, v[..., 4:9].copy()


# --- bundle adjustment ------------------------------------------------------------------------

@dataclass
class Observations:
    """M observations: camera index, object index, point in the object's frame, pixel."""

    cam: np.ndarray     # (M,) int
    obj: np.ndarray     # (M,) int
    local: np.ndarray   # (M,3)
    xy: np.ndarray      # (M,2)
    point: np.ndarray   # (M,) int, the point id (for reports and triangulation)
    frame: np.ndarray   # (M,) int, the frame index (for reports)
    weight: np.ndarray | None = None  # (M,) relative 1 / expected error, for sources of unlike precision

    def __len__(self) -> int:
        return len(self.cam)

    def select(self, mask: np.ndarray) -> "Observations":
        return Observations(self.cam[mask], self.obj[mask], self.local[mask], self.xy[mask],
                            self.point[mask], self.frame[mask], None if self.weight is None else self.weight[mask])


@dataclass
class BundleState:
    """Everything the adjuster changes. Poses: camera = world-to-camera, object = object-to-world."""

    intr: np.ndarray         # (C,9)
    cam_rvec: np.ndarray     # (C,3)
    cam_t: np.ndarray        # (C,3)
    obj_rvec: np.ndarray     # (O,3)
    obj_t: np.ndarray        # (O,3)

    def copy(self) -> "BundleState":
        return BundleState(*(a.copy() for a in (self.intr, self.cam_rvec, self.cam_t, self.obj_rvec, self.obj_t)))


@dataclass
class BundleResult:
    state: BundleState
    obs: Observations
    residuals: np.ndarray    # (M,2) pixels, of the observations kept
    outliers: int
    iterations: int
    cost_initial_px: float   # RMS before
    cost_final_px: float     # RMS after (inliers)


def residuals_of(state: BundleState, obs: Observations) -> np.ndarray:
    """Reprojection residuals (M,2) in pixels; NaN behind a camera."""
    Ro = rotvec_to_matrix(state.obj_rvec)
    Rc = rotvec_to_matrix(state.cam_rvec)
    Xw = np.einsum("mij,mj->mi", Ro[obs.obj], obs.local) + state.obj_t[obs.obj]
    Xc = np.einsum("mij,mj->mi", Rc[obs.cam], Xw) + state.cam_t[obs.cam]
    uv = project_points(Xc, state.intr[obs.cam])
    return np.where(Xc[:, 2:3] > 1e-6, uv - obs.xy, np.nan)


def bundle_adjust(state: BundleState, obs: Observations, fixed_cams: np.ndarray, fixed_objs: np.ndarray,
                  intrinsics_mask: np.ndarray | None = None,
                  obj_prior: tuple[np.ndarray, np.ndarray, float, float] | None = None,
                  loss_scale_px: float = 1.0, outlier_px: float = 4.0, max_iterations: int = 100) -> BundleResult:
    """Refine camera poses, intrinsics and object poses by robust least squares.

    fixed_cams (C,) / fixed_objs (O,): poses held fixed (the gauge). intrinsics_mask (C,9) bool:
    which intrinsic parameters are free (None: all fixed). obj_prior (rvec (O,3), t (O,3),
    sigma_rad, sigma_m): soft prior that keeps free objects near a known layout. One pass of
    outlier removal (residual above max(outlier_px, 5 x the median)) and a second solve.
    """
    adjuster = _Adjuster(len(state.cam_rvec), len(state.obj_rvec), fixed_cams, fixed_objs, intrinsics_mask,
                         obj_prior)
    initial = residuals_of(state, obs)
    rms0 = float(np.sqrt(np.nanmean(np.sum(initial**2, axis=1))))
    if adjuster.n_params == 0:
        return BundleResult(state, obs, initial, 0, 0, rms0, rms0)
    current, kept, outliers, iterations = state, obs, 0, 0
    for attempt in range(2):
        current, its = adjuster.solve(current, kept, loss_scale_px, max_iterations)
        iterations += its
        err = np.linalg.norm(residuals_of(current, kept), axis=1)
        limit = max(outlier_px, 5 * float(np.nanmedian(err)))
        bad = ~(err <= limit)
        if attempt == 1 or not bad.any():
            break
        outliers += int(bad.sum())
        kept = kept.select(~bad)
    res = residuals_of(current, kept)
    return BundleResult(current, kept, res, outliers, iterations, rms0,
                        float(np.sqrt(np.nanmean(np.sum(res**2, axis=1)))))


class _Adjuster:
    """Levenberg-Marquardt on the normal equations, with the object poses eliminated (Schur).

    Why not scipy's least_squares: on the caliscope session its sparse (LSMR) trust region had
    not converged after 100 evaluations (13 s), and its dense solver cannot take a sparse
    Jacobian. Here the Jacobian comes from finite differences in column groups (every camera's
    k-th parameter at once, then every object's), 21 vectorized evaluations whatever the number
    of cameras and frames; object poses only couple with cameras, so their 6x6 blocks are
    inverted in one batch and the system left to solve is as small as the camera parameters.
    The robust loss is soft-L1 by iteratively reweighted least squares.
    """

    def __init__(self, C: int, O: int, fixed_cams, fixed_objs, intrinsics_mask, obj_prior) -> None:
        self.C, self.O = C, O
        self.cam_free = ~np.asarray(fixed_cams, bool)
        self.obj_free = ~np.asarray(fixed_objs, bool)
        self.imask = np.zeros((C, N_INTRINSICS), bool) if intrinsics_mask is None else np.asarray(intrinsics_mask, bool)
        # camera-side slots: 6 pose + 9 intrinsics; column index per (camera, slot), -1 if fixed
        free = np.concatenate([np.repeat(self.cam_free[:, None], 6, 1), self.imask], axis=1)
        self.cam_cols = np.full((C, 6 + N_INTRINSICS), -1)
        self.cam_cols[free] = np.arange(free.sum())
        self.n_cam = int(free.sum())
        self.obj_cols = np.full((O, 6), -1)
        self.obj_cols[self.obj_free] = self.n_cam + np.arange(6 * self.obj_free.sum()).reshape(-1, 6)
        self.n_obj = 6 * int(self.obj_free.sum())
        self.n_params = self.n_cam + self.n_obj
        self.prior = obj_prior
        self.prior_objs = np.flatnonzero(self.obj_free) if obj_prior is not None else np.zeros(0, int)

    # parameters <-> state
    def _cam_block(self, s: BundleState) -> np.ndarray:
        return np.concatenate([s.cam_rvec, s.cam_t, s.intr], axis=1)

    def pack(self, s: BundleState) -> np.ndarray:
        x = np.zeros(self.n_params)
        cb = self._cam_block(s)
        sel = self.cam_cols >= 0
        x[self.cam_cols[sel]] = cb[sel]
        ob = np.concatenate([s.obj_rvec, s.obj_t], axis=1)
        sel = self.obj_cols >= 0
        x[self.obj_cols[sel]] = ob[sel]
        return x

    def unpack(self, x: np.ndarray, base: BundleState) -> BundleState:
        cb = self._cam_block(base)
        sel = self.cam_cols >= 0
        cb[sel] = x[self.cam_cols[sel]]
        ob = np.concatenate([base.obj_rvec, base.obj_t], axis=1)
        sel = self.obj_cols >= 0
        ob[sel] = x[self.obj_cols[sel]]
        return BundleState(cb[:, 6:].copy(), cb[:, :3].copy(), cb[:, 3:6].copy(), ob[:, :3].copy(), ob[:, 3:].copy())

    def residuals(self, s: BundleState, obs: Observations) -> tuple[np.ndarray, np.ndarray]:
        """(reprojection residuals (M,2) with 1e3 behind a camera, prior residuals (P,6))."""
        r = np.nan_to_num(residuals_of(s, obs), nan=1e3)
        if obs.weight is not None:
            r = r * obs.weight[:, None]
        if not len(self.prior_objs):
            return r, np.zeros((0, 6))
        rv, tv, sig_r, sig_t = self.prior
        po = self.prior_objs
        dr = matrix_to_rotvec(np.einsum("oji,ojk->oik", rotvec_to_matrix(rv[po]), rotvec_to_matrix(s.obj_rvec[po])))
        return r, np.hstack([dr / sig_r, (s.obj_t[po] - tv[po]) / sig_t])

    def jacobian(self, x: np.ndarray, s: BundleState, obs: Observations, r0: np.ndarray, p0: np.ndarray):
        """Sparse Jacobian (2M + 6P, n_params) by forward differences in column groups."""
        from scipy.sparse import coo_matrix

        M = len(obs)
        rows, cols, vals = [], [], []
        obs_rows = np.arange(2 * M).reshape(M, 2)
        # perturb slot k of every free camera (then of every free object) at once: no residual
        # depends on two cameras or two objects, so one evaluation gives a whole column group
        groups = [(self.cam_cols[:, k], obs.cam) for k in range(6 + N_INTRINSICS)]
        groups += [(self.obj_cols[:, k], obs.obj) for k in range(6)]
        for g, (col, owner) in enumerate(groups):
            free = col >= 0
            if not free.any():
                continue
            step = np.zeros(len(col))
            step[free] = 1e-6 * np.maximum(1.0, np.abs(x[col[free]]))
            dx = x.copy()
            dx[col[free]] += step[free]
            r, p = self.residuals(self.unpack(dx, s), obs)
            m = col[owner] >= 0
            rows.append(obs_rows[m].ravel())
            cols.append(np.repeat(col[owner[m]], 2))
            vals.append(((r[m] - r0[m]) / step[owner[m], None]).ravel())
            if g >= 6 + N_INTRINSICS and len(self.prior_objs):
                po = self.prior_objs
                rows.append(2 * M + np.arange(6 * len(po)))
                cols.append(np.repeat(col[po], 6))
                vals.append(((p - p0) / step[po, None]).ravel())
        n_rows = 2 * M + 6 * len(self.prior_objs)
        return coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(n_rows, self.n_params)).tocsr()

    def cost(self, r: np.ndarray, p: np.ndarray, scale: float) -> float:
        z = np.sum(r**2, axis=1) / scale**2
        return float(2 * scale**2 * np.sum(np.sqrt(1 + z) - 1) + np.sum(p**2))

    def solve(self, state: BundleState, obs: Observations, scale: float, max_iterations: int
              ) -> tuple[BundleState, int]:
        x = self.pack(state)
        r, p = self.residuals(state, obs)
        cost = self.cost(r, p, scale)
        lam = 1e-3
        it = 0
        for it in range(1, max_iterations + 1):
            J = self.jacobian(x, state, obs, r, p)
            # soft-L1 as IRLS: weight 1/sqrt(1 + (e/s)^2) per observation (both of its rows)
            w = 1 / np.sqrt(1 + np.sum(r**2, axis=1) / scale**2)
            wr = np.concatenate([np.repeat(w, 2), np.ones(p.size)])
            res = np.concatenate([r.ravel(), p.ravel()])
            Jw = J.multiply(wr[:, None]).tocsr()
            H = (J.T @ Jw).toarray() if self.n_obj == 0 else None
            g = J.T @ (wr * res)
            improved = False
            for _ in range(10):
                dx = self._step(J, Jw, H, g, lam)
                trial = self.unpack(x + dx, state)
                r_t, p_t = self.residuals(trial, obs)
                cost_t = self.cost(r_t, p_t, scale)
                if cost_t < cost:
                    improved = True
                    break
                lam *= 10
            if not improved:
                break
            x, state, r, p = x + dx, trial, r_t, p_t
            done = (cost - cost_t) < 1e-10 * cost or np.abs(dx).max() < 1e-10
            cost = cost_t
            lam = max(lam / 10, 1e-9)
            if done:
                break
        return state, it

    def _step(self, J, Jw, H_dense, g, lam: float) -> np.ndarray:
        """Solve (H + lam diag(H)) dx = -g, eliminating the object blocks first."""
        if H_dense is not None:
            A = H_dense + lam * np.diag(np.diag(H_dense)) + 1e-12 * np.eye(len(H_dense))
            return -np.linalg.solve(A, g)
        nc = self.n_cam
        Jc, Jo = J[:, :nc], J[:, nc:]
        Jwc, Jwo = Jw[:, :nc], Jw[:, nc:]
        A = (Jc.T @ Jwc).toarray()
        B = (Jc.T @ Jwo).toarray()                       # (nc, 6K)
        K = self.n_obj // 6
        Dcoo = (Jo.T @ Jwo).tocoo()  # block diagonal: one object per observation
        D = np.zeros((K, 6, 6))
        np.add.at(D, (Dcoo.row // 6, Dcoo.row % 6, Dcoo.col % 6), Dcoo.data)
        D = D + lam * np.einsum("kii->ki", D)[:, :, None] * np.eye(6) + 1e-12 * np.eye(6)
        A = A + lam * np.diag(np.diag(A)) + 1e-12 * np.eye(nc)
        Dinv = np.linalg.inv(D)
        gc, go = g[:nc], g[nc:].reshape(K, 6)
        Bk = B.reshape(nc, K, 6)
        BDinv = np.einsum("ckj,kji->cki", Bk, Dinv).reshape(nc, -1)
        S = A - BDinv @ B.T
        rhs = gc - BDinv @ go.ravel()
        dc = np.linalg.solve(S, -rhs) if nc else np.zeros(0)
        do = -np.einsum("kij,kj->ki", Dinv, go + np.einsum("cki,c->ki", Bk, dc))
        return np.concatenate([dc, do.ravel()])


# --- results ----------------------------------------------------------------------------------

@dataclass
class CameraStats:
    """Per camera: reprojection RMS and median (px), observations, frames, image coverage."""

    rms_px: float
    median_px: float
    observations: int
    frames: int
    coverage: float
    intrinsics: dict = field(default_factory=dict)


@dataclass
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
    from .intrinsics import coverage

    out = {}
    err = np.linalg.norm(residuals, axis=1)
    for c, name in enumerate(ids):
        sel = obs.cam == c
        e = err[sel]
        out[name] = CameraStats(float(np.sqrt(np.nanmean(e**2))) if sel.any() else float("nan"),
                                float(np.nanmedian(e)) if sel.any() else float("nan"), int(sel.sum()),
                                len(np.unique(obs.frame[sel])), coverage(obs.xy[sel], tuple(sizes[c])))
    return out


def _rig_from_state(ids, state: BundleState, sizes, stats: dict[str, CameraStats] | None = None) -> CameraRig:
    K, dist = unpack_intrinsics(state.intr)
    rms = None if stats is None else [stats[i].rms_px for i in ids]
    return CameraRig(tuple(ids), K, dist, rotvec_to_matrix(state.cam_rvec), state.cam_t, np.asarray(sizes), rms)


def _pnp(obj: np.ndarray, img: np.ndarray, K: np.ndarray, dist: np.ndarray,
         groups: np.ndarray | None = None, ransac_px: float = 4.0
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
    """Pose (rvec, tvec) of points obj seen at img, the inlier mask, and the inlier RMS.

    Without groups the points are one planar target, solved by IPPE (which returns both poses a
    planar target allows; the better one is kept). With groups (one label per point, e.g. the tag
    id), each group of >= 4 points proposes a pose by IPPE, the pose with most points within
    ransac_px wins and is refined on its inliers: a RANSAC over whole tags, so one mis-decoded or
    moved tag cannot pull the pose, and planar minimal sets never reach a general PnP solver.
    """
    import cv2

    obj = np.ascontiguousarray(obj, np.float64).reshape(-1, 3)
    img = np.ascontiguousarray(img, np.float64).reshape(-1, 2)
    labels = np.zeros(len(obj), int) if groups is None else np.asarray(groups)
    best = None
    for g in np.unique(labels):
        sel = labels == g
        if len(np.unique(obj[sel], axis=0)) < 4:  # repeated frames of fewer corners fit any pose
            continue
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj[sel].reshape(-1, 1, 3), img[sel].reshape(-1, 1, 2), K, dist,
                                                    flags=cv2.SOLVEPNP_IPPE)
        for rvec, tvec in zip(rvecs[:n], tvecs[:n]):
            proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
            err = np.linalg.norm(proj.reshape(-1, 2) - img, axis=1)
            inl = err < (ransac_px if groups is not None else np.inf)
            score = (inl.sum(), -np.sum(np.minimum(err, ransac_px) ** 2))
            if best is None or score > best[0]:
                best = (score, rvec, tvec, inl)
    if best is None or best[3].sum() < 4:
        return None
    _, rvec, tvec, inliers = best
    for _ in range(2):  # refine, then re-collect the inliers of the refined pose once
        rvec, tvec = cv2.solvePnPRefineLM(obj[inliers].reshape(-1, 1, 3), img[inliers].reshape(-1, 1, 2), K, dist,
                                          rvec, tvec)
        if groups is None:
            break
        proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
        inliers = np.linalg.norm(proj.reshape(-1, 2) - img, axis=1) < ransac_px
        if inliers.sum() < 4:
            return None
    proj, _ = cv2.projectPoints(obj[inliers], rvec, tvec, K, dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img[inliers]) ** 2, axis=1))))
    return rvec.ravel(), tvec.ravel(), inliers, rms


# --- board sessions ---------------------------------------------------------------------------

def calibrate_board_rig(detections: dict[str, dict[int, Detection]], sizes: dict[str, tuple[int, int]],
                        board: Board, intrinsics: dict[str, Intrinsics | tuple[np.ndarray, np.ndarray]] | None = None,
                        refine_intrinsics: bool = True, fix_k3: bool = False, allow_partial: bool = False,
                        pnp_max_px: float = 3.0, loss_scale_px: float = 1.0) -> RigCalibration:
    """Calibrate cameras that saw one board in synchronized frames.

    detections: {camera: {sync index: Detection}}; the same sync index in two cameras means the
    same instant. intrinsics: {camera: Intrinsics or (K, dist)} to start from (computed here from
    the same detections where missing). The world frame is the board in the frame where most
    cameras see it (x along the board's columns, y along its rows, z out of the board's back).
    """
    import cv2

    if board.type == "chessboard":
        raise ExtrinsicsError(f"{board.source}: a chessboard looks the same turned by 180 degrees, so "
                              f"cameras cannot agree on its corners; use a charuco or apriltag-grid board")
    names = list(detections)
    problems: dict[str, str] = {}
    K0, d0, intr_info = {}, {}, {}
    for name in names:
        given = (intrinsics or {}).get(name)
        if given is None:
            try:
                given = calibrate_intrinsics(detections[name], board, sizes[name], camera=name, fix_k3=fix_k3)
            except IntrinsicsError as exc:
                problems[name] = exc.reason
                continue
        if isinstance(given, Intrinsics):
            K0[name], d0[name], intr_info[name] = given.K, given.dist, given.summary()
        else:
            K0[name], d0[name] = np.asarray(given[0], float), np.asarray(given[1], float).ravel()[:5]
    obj_pts = board.object_points()
    # Board pose in each camera and frame (only views that PnP fits well).
    poses: dict[str, dict[int, np.ndarray]] = {}
    for name in K0:
        poses[name] = {}
        for f, det in detections[name].items():
            if len(det) < 6:
                continue
            out = _pnp(obj_pts[det.ids], det.xy, K0[name], d0[name])
            if out is not None and out[3] <= pnp_max_px:
                T = np.eye(4)
                T[:3, :3] = cv2.Rodrigues(out[0])[0]
                T[:3, 3] = out[1]
                poses[name][f] = T
    placed = _chain_cameras({n: p for n, p in poses.items() if p}, problems)
    if not placed:
        raise ExtrinsicsError("no two cameras see the board in the same frame: " + "; ".join(
            f"{n}: {m}" for n, m in problems.items()) if problems else "no camera sees the board")
    require_all(names, problems, allow_partial)
    cams = [n for n in names if n in placed]
    ci = {n: i for i, n in enumerate(cams)}
    # One object per frame seen by a placed camera; its pose from the camera seeing most points.
    frames = sorted({f for n in cams for f in poses[n]})
    fi = {f: i for i, f in enumerate(frames)}
    obj_T = np.zeros((len(frames), 4, 4))
    best_count = np.zeros(len(frames))
    for n in cams:
        for f, T in poses[n].items():
            k = len(detections[n][f])
            if k > best_count[fi[f]]:
                best_count[fi[f]] = k
                obj_T[fi[f]] = np.linalg.inv(placed[n]) @ T
    rows = [(ci[n], fi[f], det) for n in cams for f, det in detections[n].items() if f in fi]
    obs = Observations(
        cam=np.concatenate([np.full(len(d), c) for c, _, d in rows]),
        obj=np.concatenate([np.full(len(d), o) for _, o, d in rows]),
        local=np.concatenate([obj_pts[d.ids] for _, _, d in rows]),
        xy=np.concatenate([d.xy for _, _, d in rows]),
        point=np.concatenate([d.ids for _, _, d in rows]),
        frame=np.concatenate([np.full(len(d), frames[o]) for _, o, d in rows]))
    camT = np.array([placed[n] for n in cams])
    state = BundleState(np.array([pack_intrinsics(K0[n], d0[n]) for n in cams]),
                        matrix_to_rotvec(camT[:, :3, :3]), camT[:, :3, 3].copy(),
                        matrix_to_rotvec(obj_T[:, :3, :3]), obj_T[:, :3, 3].copy())
    ref = int(np.argmax([len(poses[n]) for n in cams]))
    fixed_cams = np.zeros(len(cams), bool)
    fixed_cams[ref] = True
    imask = None
    if refine_intrinsics:
        imask = np.ones((len(cams), N_INTRINSICS), bool)
        if fix_k3:
            imask[:, 8] = False
    result = bundle_adjust(state, obs, fixed_cams, np.zeros(len(frames), bool), imask,
                           loss_scale_px=loss_scale_px)
    # World frame: the board in the frame most cameras saw.
    counts = np.bincount(result.obs.obj, minlength=len(frames))
    views = np.array([len(np.unique(result.obs.cam[result.obs.obj == o])) for o in range(len(frames))])
    origin = int(np.lexsort((counts, views))[-1])
    state = _move_world(result.state, rotvec_to_matrix(result.state.obj_rvec[origin]), result.state.obj_t[origin])
    size_arr = np.array([sizes[n] for n in cams])
    stats = camera_stats(tuple(cams), result.obs, result.residuals, size_arr)
    for n in cams:
        stats[n].intrinsics = intr_info.get(n, {})
    rig = _rig_from_state(cams, state, size_arr, stats)
    return RigCalibration(rig, "board", stats, result.obs, result.residuals, result.outliers,
                          partial=bool(problems), missing=problems,
                          extra={"world_frame": f"board in frame {frames[origin]}",
                                 "frames": len(frames), "ba_rms_before_px": result.cost_initial_px})


def _move_world(state: BundleState, R: np.ndarray, t: np.ndarray) -> BundleState:
    """New world frame whose pose in the old world is (R, t): x_old = R x_new + t."""
    s = state.copy()
    Rc = rotvec_to_matrix(state.cam_rvec)
    s.cam_rvec = matrix_to_rotvec(Rc @ R)
    s.cam_t = np.einsum("cij,j->ci", Rc, t) + state.cam_t
    Ro = rotvec_to_matrix(state.obj_rvec)
    s.obj_rvec = matrix_to_rotvec(R.T @ Ro)
    s.obj_t = (state.obj_t - t) @ R
    return s


def _chain_cameras(poses: dict[str, dict[int, np.ndarray]], problems: dict[str, str]) -> dict[str, np.ndarray]:
    """World(=reference camera)-to-camera transforms from board poses seen in shared frames.

    The reference is the camera sharing most frames with the others; cameras are added along a
    maximum spanning tree (most shared frames first); each edge is a robust mean of the per-frame
    relative poses. Cameras that share no frame with the tree are reported in `problems`.
    """
    names = list(poses)
    shared = {(a, b): sorted(set(poses[a]) & set(poses[b])) for a in names for b in names if a != b}
    weight = {n: sum(len(shared[(n, m)]) for m in names if m != n) for n in names}
    if not names:
        return {}
    ref = max(names, key=lambda n: weight[n])
    placed = {ref: np.eye(4)}
    while True:
        edges = [(len(shared[(a, b)]), a, b) for a in placed for b in names if b not in placed and shared[(a, b)]]
        if not edges:
            break
        _, a, b = max(edges)
        # T_b<-a from each shared frame: T_b<-board @ inv(T_a<-board)
        rel = np.array([poses[b][f] @ np.linalg.inv(poses[a][f]) for f in shared[(a, b)]])
        R = mean_rotation(rel[:, :3, :3])
        ang = rotation_angle_deg(rel[:, :3, :3], R[None])
        keep = ang <= max(3 * np.median(ang), 1.0)
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = np.median(rel[keep, :3, 3], axis=0)
        placed[b] = T @ placed[a]
    for n in names:
        if n not in placed:
            problems[n] = "never sees the board in the same frame as the other cameras"
    return placed


def require_all(names: list[str], problems: dict[str, str], allow_partial: bool) -> None:
    """Raise, naming every camera and why, unless allow_partial (then the result leaves them out)."""
    if problems and not allow_partial:
        listed = "; ".join(f"camera {n}: {m}" for n, m in problems.items())
        raise ExtrinsicsError(f"{len(problems)} of {len(names)} cameras cannot be calibrated ({listed}); "
                              f"fix the input or pass --allow-partial for a result without them")


# --- tag sessions -----------------------------------------------------------------------------

# (the tag-placed cameras, {camera: (K, dist)}) -> {camera: features.SceneAnchors}
SceneCallback = Callable[[CameraRig, dict[str, tuple[np.ndarray, np.ndarray]]], dict]


def calibrate_tag_rig(detections: dict[str, dict[int, Detection]], sizes: dict[str, tuple[int, int]],
                      layout: TagLayout, intrinsics: dict[str, tuple[np.ndarray, np.ndarray]],
                      refine_intrinsics: bool = False, refine_tags: bool = False, tag_sigma_m: float = 0.002,
                      allow_partial: bool = False, ransac_px: float = 4.0,
                      initial_poses: dict[str, np.ndarray] | None = None,
                      scene: SceneCallback | None = None) -> RigCalibration:
    """Calibrate static cameras from tags on the walls (tags.json, world frame).

    detections: {camera: {frame: Detection}} with tag point ids (tag_id * 4 + corner);
    intrinsics: {camera: (K, dist)}. refine_tags: each tag also moves (rigidly), held to the
    layout by a prior of tag_sigma_m metres (and the matching angle), for layouts measured by hand.
    Cameras whose tags are too few for PnP are placed after the others:
    scene: (the tag-placed cameras, {camera: (K, dist)}) -> {camera: features.SceneAnchors}; each
      such camera is resected from scene points the placed cameras triangulate, and adjusted on
      those points and whatever tag corners it sees (rig.py passes features.scene_anchors);
    initial_poses: {camera: (4,4) world-to-camera} (from COLMAP) for those the scene does not place.
    """
    pid, world = layout.points()
    lookup = {int(p): i for i, p in enumerate(pid)}
    names = list(detections)
    problems: dict[str, str] = {}
    placed: dict[str, np.ndarray] = {}
    pnp_rms: dict[str, float] = {}
    short: dict[str, tuple[str, np.ndarray, np.ndarray]] = {}  # camera -> (why, known point ids, pixels)
    for name in names:
        if name not in intrinsics:
            problems[name] = "no intrinsics"
            continue
        dets = list(detections[name].values())
        ids = np.concatenate([d.ids for d in dets]) if dets else np.zeros(0, int)
        xy = np.concatenate([d.xy for d in dets]) if dets else np.zeros((0, 2))
        known = np.array([i in lookup for i in ids.tolist()], bool)
        n_tags = len(np.unique(ids[known] // 4))
        # distinct corners: the frames of a static camera repeat the same few
        if len(np.unique(ids[known])) < MIN_TAG_POINTS:
            other = np.setdiff1d(np.unique(ids // 4), layout.ids)
            why = (f"sees no tag of {layout.source}" if n_tags == 0 else
                   f"sees only {len(np.unique(ids[known]))} corner(s) of {n_tags} tag(s) of {layout.source}, "
                   f"needs {MIN_TAG_POINTS} ({MIN_TAG_POINTS // 4} whole tags)")
            if len(other):
                why += f" (it sees tags {other[:10].tolist()}, which the layout does not list)"
            short[name] = (why, ids[known], xy[known])
            continue
        K, dist = intrinsics[name]
        obj = world[[lookup[i] for i in ids[known].tolist()]]
        out = _pnp(obj, xy[known], K, dist, groups=ids[known] // 4, ransac_px=ransac_px)
        if out is None:
            problems[name] = f"tag PnP failed ({n_tags} tags): the intrinsics or the tag layout do not fit"
            continue
        T = np.eye(4)
        T[:3, :3] = rotvec_to_matrix(out[0])
        T[:3, 3] = out[1]
        placed[name] = T
        pnp_rms[name] = out[3]
    if not placed:
        require_all(names, {**problems, **{n: s[0] for n, s in short.items()}}, allow_partial)
        raise ExtrinsicsError("no camera could be placed from the tags")
    cams = [n for n in names if n in placed]
    obs, pidx = _tag_observations(detections, cams, lookup)
    obs, obj_rvec, obj_t, prior = _tag_objects(obs, pidx, world, layout, refine_tags, tag_sigma_m)
    camT = np.array([placed[n] for n in cams])
    state = BundleState(np.array([pack_intrinsics(*intrinsics[n]) for n in cams]),
                        matrix_to_rotvec(camT[:, :3, :3]), camT[:, :3, 3].copy(), obj_rvec, obj_t)
    imask = np.ones((len(cams), N_INTRINSICS), bool) if refine_intrinsics else None
    result = bundle_adjust(state, obs, np.zeros(len(cams), bool), np.full(len(obj_t), not refine_tags), imask,
                           obj_prior=prior)
    extra = {"pnp_rms_px": pnp_rms, "ba_rms_before_px": result.cost_initial_px}
    if refine_tags:
        moved = np.linalg.norm(result.state.obj_t - obj_t, axis=1)
        extra["tag_shift_m"] = {int(t): float(m) for t, m in zip(layout.ids, moved)}
    anchors, late = {}, {}
    if short and scene is not None:
        first = _rig_from_state(cams, result.state, np.array([sizes[n] for n in cams]))
        anchors = scene(first, {n: intrinsics[n] for n in short})
    for name, (why, ids_k, xy_k) in short.items():
        if name in anchors:
            late[name] = anchors[name].pose
        elif initial_poses and name in initial_poses:
            late[name] = _single_tag_pose(ids_k, world[[lookup[i] for i in ids_k.tolist()]], xy_k,
                                          intrinsics.get(name), initial_poses[name])
        else:
            problems[name] = why
    require_all(names, problems, allow_partial)
    outliers = result.outliers
    if late:
        result = _adjust_late(result, cams, late, anchors, detections, lookup, world, layout, refine_tags,
                              intrinsics, int(pid.max()) + 1)
        outliers += result.outliers
        cams = cams + list(late)
        extra["scene_points"] = {n: {"points": len(a.points), "cameras": a.matched_cameras} for n, a in anchors.items()}
        extra["colmap_poses"] = [n for n in late if n not in anchors]
    size_arr = np.array([sizes[n] for n in cams])
    stats = camera_stats(tuple(cams), result.obs, result.residuals, size_arr)
    rig = _rig_from_state(cams, result.state, size_arr, stats)
    return RigCalibration(rig, "tags", stats, result.obs, result.residuals, outliers,
                          partial=bool(problems), missing=problems, extra=extra)


def _tag_objects(obs: Observations, pidx: np.ndarray, world: np.ndarray, layout: TagLayout, refine_tags: bool,
                 tag_sigma_m: float) -> tuple[Observations, np.ndarray, np.ndarray, tuple | None]:
    """The rigid objects tag corners belong to: the world (one fixed object), or with refine_tags
    each tag on its own, starting at (and held near by a prior) its layout pose."""
    if refine_tags:
        centre = layout.corners.mean(axis=1)
        obs.obj, obs.local = pidx // 4, world[pidx] - centre[pidx // 4]
        obj_rvec, obj_t = np.zeros((len(layout.ids), 3)), centre.copy()
        return obs, obj_rvec, obj_t, (obj_rvec.copy(), obj_t.copy(), tag_sigma_m / layout.size, tag_sigma_m)
    obs.obj, obs.local = np.zeros(len(pidx), int), world[pidx]
    return obs, np.zeros((1, 3)), np.zeros((1, 3)), None


def _adjust_late(first: BundleResult, cams: list[str], late: dict[str, np.ndarray], anchors: dict,
                 detections, lookup, world, layout, refine_tags, intrinsics, first_scene_id: int) -> BundleResult:
    """Adjust the cameras placed after the tag adjustment (scene points, COLMAP), the others held
    where the tags put them. Scene points are fixed world points (one more object, the identity);
    their point ids start at first_scene_id, their frame is -1."""
    every = cams + list(late)
    obs, pidx = _tag_observations(detections, every, lookup)
    obs, _, _, _ = _tag_objects(obs, pidx, world, layout, refine_tags, 0.0)
    world_obj = len(first.state.obj_t)
    obs.weight = np.ones(len(obs))
    # inverse-error weights: tag corners fit to hundredths of a pixel, scene features to tenths, so
    # a camera's few tag corners must not be outvoted by its many scene points. The tags are
    # weighted up rather than the scene down: the robust loss keeps its scale (pixels) for the
    # scene points, which are the ones with outliers.
    tag_rms = float(np.sqrt(np.nanmean(np.sum(first.residuals**2, axis=1))))
    rows, next_id = [obs], first_scene_id
    for name, a in anchors.items():
        if name not in late:
            continue
        n, c = len(a.points), every.index(name)
        rms = float(np.sqrt(np.mean(np.sum((_project_pose(a.points, a.pose, intrinsics[name]) - a.xy) ** 2, axis=1))))
        obs.weight[obs.cam == c] = max(1.0, rms / max(tag_rms, 1e-9))
        rows.append(Observations(np.full(n, c), np.full(n, world_obj), a.points, a.xy,
                                 np.arange(next_id, next_id + n), np.full(n, -1), np.ones(n)))
        next_id += n
    obs = Observations(*(np.concatenate([getattr(r, f) for r in rows]) for f in
                         ("cam", "obj", "local", "xy", "point", "frame", "weight")))
    lateT = np.array(list(late.values()))
    s = first.state
    state = BundleState(np.concatenate([s.intr, [pack_intrinsics(*intrinsics[n]) for n in late]]),
                        np.concatenate([s.cam_rvec, matrix_to_rotvec(lateT[:, :3, :3])]),
                        np.concatenate([s.cam_t, lateT[:, :3, 3]]),
                        np.concatenate([s.obj_rvec, np.zeros((1, 3))]), np.concatenate([s.obj_t, np.zeros((1, 3))]))
    # a late camera that nothing here sees (no tag, no scene point) keeps its COLMAP pose
    free = np.isin(np.arange(len(every)), obs.cam) & (np.arange(len(every)) >= len(cams))
    return bundle_adjust(state, obs, ~free, np.ones(world_obj + 1, bool))


def _project_pose(X: np.ndarray, pose: np.ndarray, intr: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """World points (N,3) to distorted pixels (N,2) of one camera (world-to-camera pose (4,4))."""
    Xc = X @ pose[:3, :3].T + pose[:3, 3]
    return project_points(Xc, np.broadcast_to(pack_intrinsics(*intr), (len(X), N_INTRINSICS)))


def _single_tag_pose(pid: np.ndarray, obj: np.ndarray, img: np.ndarray, intr, rough: np.ndarray) -> np.ndarray:
    """A camera with one tag in view and a rough pose (from COLMAP): of the two poses a single
    planar tag allows (IPPE), the one nearer the rough pose in rotation; the rough pose itself
    when no tag is seen whole."""
    import cv2

    tags, counts = np.unique(np.unique(pid) // 4, return_counts=True)  # distinct corners per tag
    if intr is None or not (counts >= 4).any():
        return rough
    sel = pid // 4 == tags[np.argmax(counts >= 4)]
    n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj[sel].reshape(-1, 1, 3), img[sel].reshape(-1, 1, 2), intr[0], intr[1],
                                             flags=cv2.SOLVEPNP_IPPE)
    if n == 0:
        return rough
    Rs = rotvec_to_matrix(np.array(rvecs).reshape(-1, 3))
    best = int(np.argmin(rotation_angle_deg(Rs, rough[None, :3, :3])))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rs[best], np.ravel(tvecs[best])
    return T


def _tag_observations(detections: dict[str, dict[int, Detection]], cams: list[str], lookup: dict[int, int]
                      ) -> tuple[Observations, np.ndarray]:
    """Observations of the layout's tag corners (world frame, object 0) and their layout indices."""
    rows = []
    for c, n in enumerate(cams):
        for f, d in detections.get(n, {}).items():
            sel = np.array([i in lookup for i in d.ids.tolist()], bool)
            if sel.any():
                rows.append((c, f, d.ids[sel], d.xy[sel]))
    if not rows:
        raise ExtrinsicsError("no camera sees a tag of the layout")
    pidx = np.concatenate([[lookup[i] for i in r[2].tolist()] for r in rows]).astype(int)
    obs = Observations(cam=np.concatenate([np.full(len(r[2]), r[0]) for r in rows]), obj=np.zeros(len(pidx), int),
                       local=np.zeros((len(pidx), 3)), xy=np.concatenate([r[3] for r in rows]),
                       point=np.concatenate([r[2] for r in rows]),
                       frame=np.concatenate([np.full(len(r[2]), r[1]) for r in rows]))
    return obs, pidx


def evaluate_tag_rig(rig: CameraRig, detections: dict[str, dict[int, Detection]], layout: TagLayout,
                     method: str, extra: dict | None = None) -> RigCalibration:
    """Reprojection statistics of a given rig on the tag corners it sees (no adjustment)."""
    pid, world = layout.points()
    lookup = {int(p): i for i, p in enumerate(pid)}
    obs, pidx = _tag_observations(detections, list(rig.ids), lookup)
    obs.local = world[pidx]
    state = BundleState(pack_intrinsics(rig.K, rig.dist), matrix_to_rotvec(rig.R), rig.t.copy(),
                        np.zeros((1, 3)), np.zeros((1, 3)))
    res = residuals_of(state, obs)
    stats = camera_stats(rig.ids, obs, res, rig.size)
    out = CameraRig(rig.ids, rig.K, rig.dist, rig.R, rig.t, rig.size, [stats[i].rms_px for i in rig.ids])
    return RigCalibration(out, method, stats, obs, res, 0, extra=extra or {})
