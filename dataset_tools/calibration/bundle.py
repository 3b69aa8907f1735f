"""One bundle adjustment for every kind of calibration target.

Cameras see rigid objects: a board in one frame, a tag on the wall, or the fixed world. The
adjuster (`bundle_adjust`) is a Levenberg-Marquardt with a robust soft-L1 loss and a sparse
Jacobian: each residual depends on one camera and one rigid object, so finite differences need 21
vectorized evaluations per iteration whatever the number of cameras, and the object poses are
eliminated (Schur complement) before each solve. board_rig.py and tag_rig.py build its inputs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix

from manus_core.rotations import matrix_to_rotvec, rotvec_to_matrix

N_INTRINSICS = 9  # fx, fy, cx, cy, k1, k2, p1, p2, k3


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
    """K (...,3,3) and dist (...,>=5) to the adjuster's (...,9) rows (fx, fy, cx, cy, k1..k3)."""
    K = np.asarray(K)
    return np.concatenate([K[..., [0, 1, 0, 1], [0, 1, 2, 2]], np.asarray(dist)[..., :5]], axis=-1)


def unpack_intrinsics(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of pack_intrinsics: (K (...,3,3), dist (...,5))."""
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 0], K[..., 1, 1], K[..., 0, 2], K[..., 1, 2] = v[..., 0], v[..., 1], v[..., 2], v[..., 3]
    K[..., 2, 2] = 1
    return K, v[..., 4:9].copy()


@dataclass(frozen=True)
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


@dataclass(frozen=True)
class BundleState:
    """Everything the adjuster changes. Poses: camera = world-to-camera, object = object-to-world."""

    intr: np.ndarray         # (C,9)
    cam_rvec: np.ndarray     # (C,3)
    cam_t: np.ndarray        # (C,3)
    obj_rvec: np.ndarray     # (O,3)
    obj_t: np.ndarray        # (O,3)


@dataclass(frozen=True)
class BundleResult:
    """The adjusted state, the observations it kept (outliers removed) and how well they fit."""

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

