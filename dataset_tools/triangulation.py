"""Multi-view triangulation of 2D keypoints: undistortion, weighted DLT, RANSAC over views.

    points, error_px = triangulate(rig, points2d)                    # points2d (C,N,3)
    joints, error_px = triangulate_frames(rig, keypoints2d)           # keypoints2d (T,C,J,3)

points2d holds [x, y, confidence] in raw (distorted) pixels; a confidence of 0 or NaN, or a NaN
coordinate, marks a missing observation. Points that keep fewer than `min_views` usable views come
back as NaN with NaN error: nothing is ever filled in.

How (docs/triangulation.md has the details):
1. Undistortion of every observation to normalized camera coordinates: OpenCV's fixed-point
   iteration per camera, polished by Newton steps on the distortion model for all cameras at once;
   an observation whose undistortion does not converge is dropped.
2. DLT: each view adds the rows w (x P3 - P1), w (y P3 - P2) with w = confidence and P = [R | t].
   The 4x4 normal matrices of all points come from one matrix product over the cameras, and one
   batched eigh gives every point's null vector.
3. RANSAC over views (ransac=True): a hypothesis is the midpoint of the two viewing rays of a pair
   of views; the pairs are all pairs among the first views of a random view order per point (so a
   point with few views is searched exhaustively). Each hypothesis is scored against every view of
   its point (MSAC, errors in focal-length-scaled undistorted coordinates); the views within
   `threshold_px` of the best one are the inliers. Points whose best consensus is below half of
   their views get a second round with more pairs. All of it is batched over points.
4. The inliers' weighted DLT, then gating by the reprojection error in distorted pixels: the views
   farther than `threshold_px` from that solution are dropped and the point is solved again.
5. error_px: RMS reprojection error (distorted pixels) over the views that were used.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .cameras import CameraRig


class TriangulationError(ValueError):
    """Inputs that cannot be triangulated as given (shapes, camera ids, parameters)."""

    exit_code = 2


# Pairs (a, b), a < b, ordered by b then a: the first m(m-1)/2 pairs are all pairs among the
# first m views of a point's (random) view order.
def _pair_table(count: int) -> np.ndarray:
    pairs = []
    b = 1
    while len(pairs) < count:
        pairs.extend((a, b) for a in range(b))
        b += 1
    return np.array(pairs[:count], dtype=np.intp).reshape(-1, 2)


_FIRST_ROUND_PAIRS = 6  # all pairs among 4 views
_POINT_CHUNK = 512  # points scored per block: bounds the (points, hypotheses, views) arrays


def _normalized(rig: CameraRig, pixels: np.ndarray) -> np.ndarray:
    """Distorted pixels (C,N,2) to distorted normalized coordinates (K^-1 applied, skew included)."""
    fx, fy = rig.K[:, 0, 0, None], rig.K[:, 1, 1, None]
    cx, cy, skew = rig.K[:, 0, 2, None], rig.K[:, 1, 2, None], rig.K[:, 0, 1, None]
    y = (pixels[..., 1] - cy) / fy
    x = (pixels[..., 0] - cx - skew * y) / fx
    return np.stack([x, y], axis=-1)


def _newton_step(dist, x: np.ndarray, y: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One Newton step of distort(x, y) = target for any shape of x and y; dist = (k1, k2, p1, p2, k3),
    each broadcasting against x (per camera (C,1) or per observation (M,))."""
    k1, k2, p1, p2, k3 = dist
    xx, yy, xy_ = x * x, y * y, x * y
    r2 = xx + yy
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    d_radial = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d radial / d r2
    fx_ = x * radial + 2 * p1 * xy_ + p2 * (r2 + 2 * xx) - target[..., 0]
    fy_ = y * radial + p1 * (r2 + 2 * yy) + 2 * p2 * xy_ - target[..., 1]
    jxx = radial + 2 * xx * d_radial + 2 * p1 * y + 6 * p2 * x
    jyy = radial + 2 * yy * d_radial + 6 * p1 * y + 2 * p2 * x
    jxy = 2 * xy_ * d_radial + 2 * p1 * x + 2 * p2 * y  # the Jacobian is symmetric
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_det = 1.0 / (jxx * jyy - jxy * jxy)
    return x - (jyy * fx_ - jxy * fy_) * inv_det, y - (jxx * fy_ - jxy * fx_) * inv_det


# A Newton step smaller than this (normalized units, ~1e-4 px) leaves an error of its square.
_NEWTON_TOL = 1e-7
_NEWTON_STEPS = 8


def undistort_points(rig: CameraRig, pixels: np.ndarray) -> np.ndarray:
    """Distorted pixels (C,N,2) to undistorted normalized coordinates (C,N,2).

    NaN in, NaN out; an observation whose undistortion does not converge (outside the region where
    the distortion model can be inverted) is NaN as well.
    """
    import cv2

    pixels = np.asarray(pixels, dtype=np.float64)
    target = _normalized(rig, pixels)
    out = np.empty(pixels.shape)
    eye = np.eye(3)
    for c in range(len(rig)):  # one OpenCV call per camera, vectorized over its points (NaN stays NaN)
        # On normalized input with an identity camera matrix OpenCV inverts the distortion only.
        out[c] = cv2.undistortPoints(target[c].reshape(-1, 1, 2), eye, rig.dist[c]).reshape(-1, 2)
    # OpenCV stops after 5 fixed-point iterations (up to 0.3 px off at the corners of a strong
    # lens). Newton steps on the distortion model polish that to rounding error; observations that
    # are still moving after a few steps have no inverse and are dropped.
    x, y = _newton_step(rig.dist.T[:, :, None], out[..., 0], out[..., 1], target)
    moved = np.maximum(np.abs(x - out[..., 0]), np.abs(y - out[..., 1]))
    out[..., 0], out[..., 1] = x, y
    cams, points = np.nonzero(moved >= _NEWTON_TOL)  # NaN compares False: missing stays missing
    if len(cams):  # the few that need more steps, one row per observation
        dist, goal = rig.dist[cams].T.copy(), target[cams, points]
        x, y = out[cams, points, 0], out[cams, points, 1]
        active = np.arange(len(cams))
        for _ in range(_NEWTON_STEPS):
            nx, ny = _newton_step(dist[:, active], x[active], y[active], goal[active])
            moved = np.maximum(np.abs(nx - x[active]), np.abs(ny - y[active]))
            x[active], y[active] = nx, ny
            active = active[~(moved < _NEWTON_TOL)]
            if not len(active):
                break
        x[active] = y[active] = np.nan
        out[cams, points, 0], out[cams, points, 1] = x, y
    return out


def _project(rig: CameraRig, X: np.ndarray) -> np.ndarray:
    """World points (N,3) to distorted pixels (C,N,2), NaN behind a camera: CameraRig.project with
    the rotation as matrix products (einsum is several times slower on a million points)."""
    Xt = X.T
    xc, yc, zc = (rig.R[:, i, :] @ Xt + rig.t[:, i, None] for i in range(3))
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = np.where(zc > 0, 1.0 / zc, np.nan)
    xd = rig.distort(np.stack([xc * inv_z, yc * inv_z], axis=-1))
    K = rig.K
    u = K[:, 0, 0, None] * xd[..., 0] + K[:, 0, 1, None] * xd[..., 1] + K[:, 0, 2, None]
    v = K[:, 1, 1, None] * xd[..., 1] + K[:, 1, 2, None]
    return np.stack([u, v], axis=-1)


def _world_normalization(rig: CameraRig) -> tuple[np.ndarray, float]:
    """Centre and scale that bring the camera centres around the origin at unit distance.

    Solving in these coordinates keeps the normal matrices well conditioned whatever the units
    and the placement of the world frame.
    """
    centers = rig.centers
    center = centers.mean(axis=0)
    scale = float(np.linalg.norm(centers - center, axis=1).mean())
    return center, (scale if scale > 0 else 1.0)


def _normalized_projections(rig: CameraRig, center: np.ndarray, scale: float) -> np.ndarray:
    """[R | t] acting on normalized world points X' with X = scale X' + center, (C,3,4)."""
    return np.concatenate([rig.R * scale, (rig.R @ center + rig.t)[:, :, None]], axis=2)


def _row_products(P: np.ndarray) -> np.ndarray:
    """Per camera, the four 4x4 blocks whose combination is one view's normal matrix, (4,C,16).

    For a view with weight w and point (x, y), the rows w (x p3 - p1) and w (y p3 - p2) give
    w^2 [(x^2 + y^2) p3p3' - x (p3p1' + p1p3') - y (p3p2' + p2p3') + p1p1' + p2p2'].
    """
    p1, p2, p3 = P[:, 0], P[:, 1], P[:, 2]

    def outer(a, b):
        return np.einsum("ci,cj->cij", a, b).reshape(len(P), 16)

    return np.stack([outer(p3, p3), -(outer(p3, p1) + outer(p1, p3)), -(outer(p3, p2) + outer(p2, p3)),
                     outer(p1, p1) + outer(p2, p2)])


def _normal_matrices(blocks: np.ndarray, xy: np.ndarray, w2: np.ndarray) -> np.ndarray:
    """Normal matrices (N,4,4) of all points at once; xy (C,N,2), w2 (C,N) squared weights (0 = unused)."""
    x = np.where(w2 > 0, xy[..., 0], 0.0)
    y = np.where(w2 > 0, xy[..., 1], 0.0)
    coef = np.stack([w2 * (x * x + y * y), w2 * x, w2 * y, w2])  # (4,C,N)
    n_blocks, n_cams = blocks.shape[:2]
    # (16, 4C) @ (4C, N) keeps both operands C-ordered: several times faster than (N, 4C) @ (4C, 16).
    m = blocks.reshape(n_blocks * n_cams, 16).T @ coef.reshape(n_blocks * n_cams, -1)
    return np.ascontiguousarray(m.T).reshape(-1, 4, 4)


def _solve_homogeneous(m: np.ndarray) -> np.ndarray:
    """Null vectors of the normal matrices (N,4,4) -> inhomogeneous points (N,3); NaN at infinity."""
    out = np.full((len(m), 3), np.nan)
    ok = np.isfinite(m).all(axis=(1, 2))
    if ok.any():
        _, vectors = np.linalg.eigh(m[ok])
        v = vectors[:, :, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            X = v[:, :3] / v[:, 3:]
        out[ok] = np.where(np.abs(v[:, 3:]) > 1e-12, X, np.nan)
    return out


def _rays(rig: CameraRig, xy: np.ndarray) -> np.ndarray:
    """World directions (C,N,3) of the viewing rays through undistorted normalized points (C,N,2)."""
    xyh = np.concatenate([xy, np.ones(xy.shape[:2] + (1,))], axis=2)
    return np.matmul(xyh, rig.R)  # R' (x, y, 1) for every point: row vector times R


def _midpoints(origins: np.ndarray, rays: np.ndarray, views: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Two-view hypotheses (n,K,3): midpoints of the closest points of the two rays of each pair.

    Closed form and a few dozen flops per pair, where a DLT per hypothesis would need a solve;
    the hypotheses only have to be good enough to find the inliers, which the DLT then solves.
    views (n,K,2) camera indices, points (n,) point indices into rays (C,N,3).
    """
    p = points[:, None]
    o1, o2 = origins[views[..., 0]], origins[views[..., 1]]
    d1, d2 = rays[views[..., 0], p], rays[views[..., 1], p]
    w = o1 - o2
    a, b, c = (d1 * d1).sum(-1), (d1 * d2).sum(-1), (d2 * d2).sum(-1)
    d, e = (d1 * w).sum(-1), (d2 * w).sum(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / (a * c - b * b)  # 0 for parallel rays: no hypothesis (inf/NaN, scored out)
        s = (b * e - c * d) * inv
        t = (a * e - b * d) * inv
    return 0.5 * (o1 + s[..., None] * d1 + o2 + t[..., None] * d2)


def _hypothesis_errors(rig: CameraRig, X: np.ndarray, x_obs: np.ndarray, y_obs: np.ndarray) -> np.ndarray:
    """Squared reprojection errors (n,K,C) of hypotheses X (n,K,3) against observations (n,C), in
    approximate pixels; NaN where the observation is missing or the point is behind the camera.

    Measured between undistorted normalized coordinates scaled by the focal lengths, so no
    distortion model is evaluated per hypothesis.
    """
    n, k = X.shape[:2]
    flat = X.reshape(-1, 3)
    xc, yc, zc = ((flat @ rig.R[:, i, :].T + rig.t[:, i]).reshape(n, k, -1) for i in range(3))
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = np.where(zc > 0, 1.0 / zc, np.nan)
    ex = (xc * inv_z - x_obs[:, None]) * rig.K[:, 0, 0]
    ey = (yc * inv_z - y_obs[:, None]) * rig.K[:, 1, 1]
    return ex * ex + ey * ey


def _ransac_inliers(rig: CameraRig, xy: np.ndarray, usable: np.ndarray, threshold_px: float, iterations: int,
                    rng: np.random.Generator) -> np.ndarray:
    """Inlier views (C,N) of each point's best two-view hypothesis (MSAC score over all its views)."""
    n_cams, n_points = usable.shape
    threshold2 = threshold_px ** 2
    n_views = usable.sum(axis=0)
    rays = _rays(rig, xy)
    origins = rig.centers
    x_obs, y_obs = np.ascontiguousarray(xy[..., 0].T), np.ascontiguousarray(xy[..., 1].T)  # (N,C)
    # A random view order per point, usable views first.
    order = np.argsort(rng.random((n_points, n_cams)) + (~usable.T) * 2.0, axis=1)
    pairs = _pair_table(max(iterations, 1))
    pairs = pairs[pairs[:, 1] < n_cams]
    inliers = np.zeros((n_points, n_cams), dtype=bool)
    best_cost = np.full(n_points, np.inf)

    def run(points: np.ndarray, pair_rows: np.ndarray) -> None:
        for start in range(0, len(points), _POINT_CHUNK):
            idx = points[start:start + _POINT_CHUNK]
            views = order[idx][:, pair_rows]  # (n,K,2)
            X = _midpoints(origins, rays, views, idx)
            e2 = _hypothesis_errors(rig, X, x_obs[idx], y_obs[idx])
            # MSAC: a view costs its squared error, capped at the threshold; missing views and
            # views behind the camera (NaN) cost the cap, the same for every hypothesis of a point.
            cost = np.fmin(e2, threshold2).sum(axis=2)
            possible = pair_rows[None, :, 1] < n_views[idx, None]  # both views of the pair usable
            cost[~(possible & np.isfinite(X).all(axis=-1))] = np.inf
            k = np.argmin(cost, axis=1)
            rows = np.arange(len(idx))
            better = cost[rows, k] < best_cost[idx]
            with np.errstate(invalid="ignore"):
                inliers[idx[better]] = e2[rows, k][better] < threshold2
            best_cost[idx[better]] = cost[rows, k][better]

    candidates = np.flatnonzero(n_views >= 2)
    run(candidates, pairs[:_FIRST_ROUND_PAIRS])
    if len(pairs) > _FIRST_ROUND_PAIRS:
        # Points whose consensus is not yet a majority of their views, and that have more views
        # than the first round looked at, try the remaining pairs.
        found = inliers[candidates].sum(axis=1)
        weak = candidates[(found * 2 < n_views[candidates]) & (n_views[candidates] > 4)]
        if len(weak):
            run(weak, pairs[_FIRST_ROUND_PAIRS:])
    return inliers.T


def _reprojection_errors(rig: CameraRig, X: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Pixel distance (C,N) between projections of X (N,3) and observations; NaN behind a camera."""
    d = _project(rig, X)
    d -= pixels
    return np.hypot(d[..., 0], d[..., 1])


def _check_inputs(rig: CameraRig, points2d, camera_ids: Sequence[str] | None) -> tuple[CameraRig, np.ndarray]:
    try:
        pts = np.asarray(points2d, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise TriangulationError(f"triangulate: points2d is not a numeric array ({exc})") from None
    if pts.ndim != 3 or pts.shape[2] not in (2, 3):
        raise TriangulationError(f"triangulate: points2d must be (C, N, 3) [x, y, confidence], got shape {pts.shape}")
    if camera_ids is not None:
        camera_ids = [str(c) for c in camera_ids]
        if len(camera_ids) != pts.shape[0]:
            raise TriangulationError(f"triangulate: {len(camera_ids)} camera ids for "
                                     f"{pts.shape[0]} cameras of points2d")
        missing = [c for c in camera_ids if c not in rig.ids]
        if missing:
            raise TriangulationError(f"triangulate: cameras {missing} are not in the calibration "
                                     f"({len(rig)} cameras: {', '.join(rig.ids[:8])}{'...' if len(rig) > 8 else ''})")
        rig = rig.subset(camera_ids)
    if pts.shape[0] != len(rig):
        raise TriangulationError(f"triangulate: points2d has {pts.shape[0]} cameras but the calibration has "
                                 f"{len(rig)}; pass camera_ids to say which camera each row is")
    if pts.shape[2] == 2:
        pts = np.concatenate([pts, np.ones(pts.shape[:2] + (1,))], axis=2)
    return rig, pts


def triangulate(rig: CameraRig, points2d: np.ndarray, ransac: bool = True, *, threshold_px: float = 10.0,
                iterations: int = 28, min_views: int = 2, max_error_px: float | None = None,
                camera_ids: Sequence[str] | None = None, seed: int = 0,
                return_inliers: bool = False):
    """Triangulate N points seen by the C cameras of `rig`.

    points2d: (C,N,3) [x, y, confidence] in raw (distorted) pixels, or (C,N,2) for confidence 1;
    a confidence of 0 or NaN, or a NaN coordinate, marks a missing observation.
    ransac: reject outlier views (RANSAC over view pairs, then gating at `threshold_px`); with False,
    every usable view is used (a plain confidence-weighted DLT).
    threshold_px: inlier distance in pixels. iterations: at most this many view pairs per point.
    min_views: points with fewer usable (ransac: inlier) views are NaN.
    max_error_px: points whose RMS reprojection error exceeds it are NaN as well.
    camera_ids: the calibration's id of each row of points2d (default: the rig's own order).
    seed: the random view order of RANSAC (results are deterministic for a seed).
    return_inliers: also return the (C,N) bool mask of the views each point was solved from.

    Returns points (N,3) in world units and error_px (N,), the RMS reprojection error in pixels
    over the views used; both NaN where a point could not be triangulated.
    """
    rig, pts = _check_inputs(rig, points2d, camera_ids)
    if min_views < 2:
        raise TriangulationError(f"triangulate: min_views = {min_views}, at least 2 views are needed")
    if not threshold_px > 0:
        raise TriangulationError(f"triangulate: threshold_px = {threshold_px!r} must be > 0")
    pixels, conf = pts[..., :2], pts[..., 2]
    with np.errstate(invalid="ignore"):
        # x + y is finite exactly when both are (inf - inf is NaN).
        usable = np.isfinite(pixels[..., 0] + pixels[..., 1]) & (conf > 0)
    pixels = np.where(usable[..., None], pixels, np.nan)
    xy = undistort_points(rig, pixels)
    usable &= ~np.isnan(xy[..., 0])

    center, scale = _world_normalization(rig)
    blocks = _row_products(_normalized_projections(rig, center, scale))
    weights2 = np.where(usable, conf, 0.0) ** 2

    def solve(views: np.ndarray, idx=slice(None)) -> tuple[np.ndarray, np.ndarray]:
        """Weighted DLT of points idx from their views (C,n); returns X (n,3) and errors (C,n)."""
        m = _normal_matrices(blocks, xy[:, idx], np.where(views, weights2[:, idx], 0.0))
        X = _solve_homogeneous(m) * scale + center
        return X, _reprojection_errors(rig, X, pixels[:, idx])

    if ransac:
        used = _ransac_inliers(rig, xy, usable, threshold_px, iterations, np.random.default_rng(seed))
        X, errors = solve(used)
        # Gating: keep the views within the threshold of the inliers' solution (distorted pixels
        # now, exactly), and solve again the points whose views changed.
        with np.errstate(invalid="ignore"):
            gated = usable & (errors < threshold_px)
        changed = np.flatnonzero((gated != used).any(axis=0))
        used = gated
        if len(changed):
            X[changed], errors[:, changed] = solve(used[:, changed], changed)
    else:
        used = usable
        X, errors = solve(used)
    n_used = used.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        sq = np.square(errors, out=errors)
        sq[~used] = 0.0
        error_px = np.sqrt(sq.sum(axis=0) / n_used)
    # A NaN error means a used view lies behind its camera: such a solution is no point at all.
    bad = (n_used < min_views) | ~np.isfinite(error_px) | ~np.isfinite(X).all(axis=1)
    if max_error_px is not None:
        bad |= error_px > max_error_px
    X[bad] = np.nan
    error_px[bad] = np.nan
    used = used & ~bad
    if return_inliers:
        return X, error_px, used
    return X, error_px


def triangulate_frames(rig: CameraRig, keypoints2d: np.ndarray, ransac: bool = True, **kwargs):
    """Triangulate keypoints of many frames at once: keypoints2d (T,C,J,3) -> ((T,J,3), (T,J)).

    One call over all frames is much faster than a call per frame. Keyword arguments are those of
    `triangulate`; with return_inliers=True a third array (T,C,J) bool comes back.
    """
    kp = np.asarray(keypoints2d, dtype=np.float64)
    if kp.ndim != 4 or kp.shape[3] not in (2, 3):
        raise TriangulationError(f"triangulate_frames: keypoints2d must be (T, C, J, 3), got shape {kp.shape}")
    n_t, n_c, n_j = kp.shape[:3]
    flat = kp.transpose(1, 0, 2, 3).reshape(n_c, n_t * n_j, kp.shape[3])
    result = triangulate(rig, flat, ransac, **kwargs)
    X, err = result[0].reshape(n_t, n_j, 3), result[1].reshape(n_t, n_j)
    if len(result) == 3:
        return X, err, result[2].reshape(n_c, n_t, n_j).transpose(1, 0, 2)
    return X, err
