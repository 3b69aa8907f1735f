"""Multi-view triangulation of 2D keypoints: undistortion, weighted DLT, RANSAC over views.

    points, error_px = triangulate(rig, points2d)                    # points2d (C,N,3)
    joints, error_px = triangulate_frames(rig, keypoints2d)           # keypoints2d (T,C,J,3)

points2d holds [x, y, confidence] in raw (distorted) pixels; a confidence of 0 or NaN, or a NaN
coordinate, marks a missing observation. Points that keep fewer than `min_views` usable views come
back as NaN with NaN error: nothing is ever filled in.

How (docs/triangulation.md has the details):
1. Undistortion of every observation to normalized camera coordinates (dataset_tools.undistort);
   an observation whose undistortion does not converge is dropped.
2. DLT: each view adds the rows w (x P3 - P1), w (y P3 - P2) with w = confidence and P = [R | t].
   The 4x4 normal matrices of a block of points come from one matrix product over the cameras;
   their null vectors from a closed-form LDL' and inverse iteration (eigh where that does not settle).
3. RANSAC over views (ransac=True): a hypothesis is the midpoint of the two viewing rays of a pair
   of views; the pairs are all pairs among the first views of a random view order per point (so a
   point with few views is searched exhaustively). Each hypothesis is scored against every view of
   its point (MSAC, errors in focal-length-scaled undistorted coordinates); the views within
   `threshold_px` of the best one are the inliers. Points whose best consensus is below half of
   their views get a second round with more pairs. All of it is batched over points.
4. The inliers' weighted DLT, then gating by the reprojection error in distorted pixels: the views
   farther than `threshold_px` from that solution are dropped and the point is solved again.
5. error_px: RMS reprojection error (distorted pixels) over the views that were used.
All elementwise stages run in blocks of points small enough for their temporaries to stay in cache.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from manus_core.cameras import CameraRig
from manus_core.errors import TriangulationError

from .undistort import point_blocks, undistort_columns


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
_RANSAC_ELEMENTS = 1 << 16  # (points, hypotheses, views) scored per block


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


_UPPER = np.triu_indices(4)  # the 10 entries of a symmetric 4x4 matrix, row by row


def _row_products(P: np.ndarray) -> np.ndarray:
    """Per camera, the four symmetric 4x4 blocks whose combination is one view's normal matrix, as
    the (10, 4C) matrix of their upper triangles (block k of camera c in column k C + c).

    For a view with weight w and point (x, y), the rows w (x p3 - p1) and w (y p3 - p2) give
    w^2 [(x^2 + y^2) p3p3' - x (p3p1' + p1p3') - y (p3p2' + p2p3') + p1p1' + p2p2'].
    """
    p1, p2, p3 = P[:, 0], P[:, 1], P[:, 2]

    def sym(a, b):  # upper triangle of a b' + b a'
        o = a[:, :, None] * b[:, None, :]
        return (o + o.transpose(0, 2, 1))[:, _UPPER[0], _UPPER[1]]

    blocks = np.stack([sym(p3, p3) / 2, -sym(p3, p1), -sym(p3, p2), (sym(p1, p1) + sym(p2, p2)) / 2])
    return np.ascontiguousarray(blocks.reshape(-1, 10).T)


def _ldl(m: np.ndarray) -> np.ndarray:
    """LDL' factors of symmetric 4x4 matrices given as upper triangles m (10,n), without pivoting:
    (l10, l20, l30, l21, l31, l32, d3/d0, d3/d1, d3/d2) as (9,n).

    The pivots come as ratios to the last one, d3, which is ~0 for a normal matrix of consistent
    views: inverse iteration scaled by d3 then stays finite even for exact data (d3 = 0).
    """
    a00, a01, a02, a03, a11, a12, a13, a22, a23, a33 = m
    l10, l20, l30 = a01 / a00, a02 / a00, a03 / a00
    d1 = a11 - l10 * a01
    t21, t31 = a12 - l20 * a01, a13 - l30 * a01
    l21, l31 = t21 / d1, t31 / d1
    d2 = a22 - l20 * a02 - l21 * t21
    t32 = a23 - l30 * a02 - l31 * t21
    l32 = t32 / d2
    d3 = a33 - l30 * a03 - l31 * t31 - l32 * t32
    return np.stack([l10, l20, l30, l21, l31, l32, d3 / a00, d3 / d1, d3 / d2])


def _inverse_step(F: np.ndarray, w: np.ndarray) -> np.ndarray:
    """One step of inverse iteration, w <- d3 M^-1 w normalized, with M = L D L' given by F (9,n)."""
    l10, l20, l30, l21, l31, l32, r0, r1, r2 = F
    z0 = w[0]
    z1 = w[1] - l10 * z0
    z2 = w[2] - l20 * z0 - l21 * z1
    z3 = w[3] - l30 * z0 - l31 * z1 - l32 * z2
    z0, z1, z2 = z0 * r0, z1 * r1, z2 * r2
    v2 = z2 - l32 * z3
    v1 = z1 - l21 * v2 - l31 * z3
    v0 = z0 - l10 * v1 - l20 * v2 - l30 * z3
    v = np.stack([v0, v1, v2, z3])
    return v / np.sqrt((v * v).sum(axis=0))


# Inverse iteration stops when a step turns the vector by less than this: the error left is about
# this times lambda_1 / lambda_2 (~1e-5), below rounding. Points still turning after _INVERSE_STEPS
# have views that disagree (outliers without RANSAC): eigh solves those.
_INVERSE_TOL = 1e-9
_INVERSE_STEPS = 4


def _null_points(m: np.ndarray) -> np.ndarray:
    """Points (n,3) from the null vectors (eigenvectors of the smallest eigenvalue, what an SVD of
    the DLT rows gives) of symmetric 4x4 normal matrices given as upper triangles m (10,n); NaN at
    infinity or where the views do not fix a point.

    Closed form and elementwise over n, several times faster than a batched np.linalg.eigh: inverse
    iteration from e4 on an LDL' factorization. Its first step is the inhomogeneous solution (X, 1);
    each further step shrinks the remaining error by lambda_1 / lambda_2, which is ~1e-5 for
    consistent views, so two or three steps reach rounding error.
    """
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        F = _ldl(m)
        w = np.zeros((4, m.shape[1]))
        w[3] = 1.0
        w = _inverse_step(F, w)
        active = np.arange(m.shape[1])
        for _ in range(_INVERSE_STEPS):
            prev = w[:, active]
            step = _inverse_step(F[:, active], prev)
            # The sign of a null vector is free (and d3 may be slightly negative): compare both.
            turned = np.abs(step - prev * np.sign((step * prev).sum(axis=0))).max(axis=0)
            w[:, active] = step
            active = active[turned > _INVERSE_TOL]  # NaN leaves the loop too
            if not len(active):
                break
        if len(active):
            M = np.empty((len(active), 4, 4))
            M[:, _UPPER[0], _UPPER[1]] = M[:, _UPPER[1], _UPPER[0]] = m[:, active].T
            w[:, active] = np.linalg.eigh(M)[1][:, :, 0].T
        points = (w[:3] / w[3]).T
    points[~(np.abs(w[3]) > 1e-12)] = np.nan  # at infinity, or NaN
    return points


def _dlt(blocks: np.ndarray, x: np.ndarray, y: np.ndarray, w2: np.ndarray) -> np.ndarray:
    """Weighted DLT of n points, in normalized world coordinates (n,3); x, y (C,n) undistorted
    normalized coordinates (finite, 0 where unused), w2 (C,n) squared weights (0 = unused).

    The normal matrices are one product (10, 4C) @ (4C, n) of the per-camera blocks and the
    per-view coefficients w^2 (x^2 + y^2), w^2 x, w^2 y, w^2.
    """
    wx, wy = w2 * x, w2 * y
    return _null_points(blocks @ np.concatenate([wx * x + wy * y, wx, wy, w2]))


def _rays(rig: CameraRig, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """World directions (C,N,3) of the viewing rays through undistorted normalized points x, y (C,N)."""
    xyh = np.stack([x, y, np.ones_like(x)], axis=2)
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


def _focal_projections(rig: CameraRig) -> tuple[np.ndarray, np.ndarray]:
    """The rows fx r1, fy r2, r3 of every camera as a (3, 3C) matrix (columns i C + c) and the
    matching (3C,) translations: one product gives the camera coordinates, scaled to pixels, of
    points in all cameras."""
    f = np.stack([rig.K[:, 0, 0], rig.K[:, 1, 1], np.ones(len(rig))])  # (3,C)
    rows = rig.R.transpose(1, 0, 2) * f[:, :, None]  # (3,C,3)
    return np.ascontiguousarray(rows.reshape(-1, 3).T), (rig.t.T * f).ravel()


def _hypothesis_errors(projection: tuple[np.ndarray, np.ndarray], X: np.ndarray, u_obs: np.ndarray,
                       v_obs: np.ndarray) -> np.ndarray:
    """Squared reprojection errors (n,K,C) of hypotheses X (n,K,3) against observations (n,C) given
    as undistorted normalized coordinates times the focal lengths; approximate pixels, NaN where
    the observation is missing or the point is behind the camera.

    No distortion model is evaluated per hypothesis: the observations were undistorted once.
    """
    n, k = X.shape[:2]
    rows, t = projection
    n_cams = len(t) // 3
    Y = X.reshape(-1, 3) @ rows
    Y += t
    Y = Y.reshape(n, k, 3, n_cams)
    with np.errstate(divide="ignore", invalid="ignore"):
        zc = Y[:, :, 2]
        inv_z = np.where(zc > 0, 1.0 / zc, np.nan)
        ex = Y[:, :, 0] * inv_z
        ex -= u_obs[:, None]
        ey = Y[:, :, 1] * inv_z
        ey -= v_obs[:, None]
        ex *= ex
        ey *= ey
        ex += ey
    return ex


def _ransac_inliers(rig: CameraRig, x: np.ndarray, y: np.ndarray, usable: np.ndarray, threshold_px: float,
                    iterations: int, rng: np.random.Generator) -> np.ndarray:
    """Inlier views (C,N) of each point's best two-view hypothesis (MSAC score over all its views)."""
    n_cams, n_points = usable.shape
    threshold2 = threshold_px ** 2
    n_views = usable.sum(axis=0)
    rays = _rays(rig, x, y)
    origins = rig.centers
    projection = _focal_projections(rig)
    u_obs = np.ascontiguousarray((x * rig.K[:, 0, 0, None]).T)  # (N,C), NaN where missing
    v_obs = np.ascontiguousarray((y * rig.K[:, 1, 1, None]).T)
    # A random view order per point, usable views first.
    order = np.argsort(rng.random((n_points, n_cams)) + (~usable.T) * 2.0, axis=1)
    pairs = _pair_table(max(iterations, 1))
    pairs = pairs[pairs[:, 1] < n_cams]
    inliers = np.zeros((n_points, n_cams), dtype=bool)
    best_cost = np.full(n_points, np.inf)

    def run(points: np.ndarray, pair_rows: np.ndarray) -> None:
        chunk = max(1, _RANSAC_ELEMENTS // max(1, len(pair_rows) * n_cams))
        for start in range(0, len(points), chunk):
            idx = points[start:start + chunk]
            views = order[idx][:, pair_rows]  # (n,K,2)
            X = _midpoints(origins, rays, views, idx)
            e2 = _hypothesis_errors(projection, X, u_obs[idx], v_obs[idx])
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


def _reprojection_errors(rig: CameraRig, X: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """Pixel distance (C,n) between the projections of X (n,3) and observations px, py (C,n);
    NaN behind a camera."""
    R, t, K = rig.R, rig.t, rig.K
    Xt = X.T
    with np.errstate(divide="ignore", invalid="ignore"):
        xc, yc, zc = (R[:, i, :] @ Xt + t[:, i, None] for i in range(3))
        inv_z = np.where(zc > 0, 1.0 / zc, np.nan)
        xd = rig.distort(np.stack([xc * inv_z, yc * inv_z], axis=-1))
        du = K[:, 0, 0, None] * xd[..., 0] + K[:, 0, 1, None] * xd[..., 1] + K[:, 0, 2, None] - px
        dv = K[:, 1, 1, None] * xd[..., 1] + K[:, 1, 2, None] - py
        return np.sqrt(du * du + dv * dv)


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
    n_cams, n_points = pts.shape[:2]
    center, scale = _world_normalization(rig)
    blocks = _row_products(_normalized_projections(rig, center, scale))
    # The elementwise stages go block by block, so that the temporaries of a large take stay in
    # the CPU cache; RANSAC takes all points at once (it blocks its own arrays), so that the points
    # that need a second round are one batch.
    spans = point_blocks(n_cams, n_points)
    px, py, x, y = (np.empty((n_cams, n_points)) for _ in range(4))
    usable = np.empty((n_cams, n_points), dtype=bool)
    for b in spans:
        px[:, b], py[:, b], x[:, b], y[:, b], usable[:, b] = _observations(rig, pts[:, b])
    if ransac:
        used = _ransac_inliers(rig, x, y, usable, threshold_px, iterations, np.random.default_rng(seed))
    else:
        used = usable.copy()
    X, error_px = np.empty((n_points, 3)), np.empty(n_points)
    for b in spans:
        X[b], error_px[b], used[:, b] = _solve_block(
            rig, blocks, center, scale, px[:, b], py[:, b], x[:, b], y[:, b], pts[:, b, 2], usable[:, b],
            used[:, b], threshold_px if ransac else None)
    n_used = used.sum(axis=0)
    # A NaN error means a used view lies behind its camera: such a solution is no point at all.
    bad = (n_used < min_views) | ~np.isfinite(error_px) | ~np.isfinite(X).all(axis=1)
    if max_error_px is not None:
        bad |= error_px > max_error_px
    X[bad] = np.nan
    error_px[bad] = np.nan
    used &= ~bad
    if return_inliers:
        return X, error_px, used
    return X, error_px


def _observations(rig: CameraRig, pts: np.ndarray) -> tuple[np.ndarray, ...]:
    """pts (C,n,3) -> pixels px, py, undistorted normalized x, y (NaN where missing) and the mask of
    usable observations, each (C,n)."""
    px, py, conf = pts[..., 0], pts[..., 1], pts[..., 2]
    with np.errstate(invalid="ignore"):
        # x + y is finite exactly when both are (inf - inf is NaN).
        usable = np.isfinite(px + py) & (conf > 0)
    px, py = np.where(usable, px, np.nan), np.where(usable, py, np.nan)
    x, y = undistort_columns(rig, px, py)
    return px, py, x, y, usable & ~np.isnan(x)


def _solve_block(rig: CameraRig, blocks: np.ndarray, center: np.ndarray, scale: float, px: np.ndarray,
                 py: np.ndarray, x: np.ndarray, y: np.ndarray, conf: np.ndarray, usable: np.ndarray,
                 views: np.ndarray, gate_px: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The weighted DLT of one block of points from `views` (C,n), then (gate_px given) gating:
    the usable views within gate_px of that solution are kept and the points whose views changed
    are solved again. Returns points (n,3), RMS error (n,) and the views used (C,n)."""
    weights2 = np.where(usable, conf, 0.0) ** 2
    x0, y0 = np.where(usable, x, 0.0), np.where(usable, y, 0.0)  # the DLT's unused views weigh 0

    def solve(views: np.ndarray, idx=slice(None)) -> tuple[np.ndarray, np.ndarray]:
        X = _dlt(blocks, x0[:, idx], y0[:, idx], np.where(views, weights2[:, idx], 0.0)) * scale + center
        return X, _reprojection_errors(rig, X, px[:, idx], py[:, idx])

    X, errors = solve(views)
    if gate_px is not None:
        # Distorted pixels now, exactly (RANSAC scored in undistorted coordinates).
        with np.errstate(invalid="ignore"):
            gated = usable & (errors < gate_px)
        changed = np.flatnonzero((gated != views).any(axis=0))
        views = gated
        if len(changed):
            X[changed], errors[:, changed] = solve(views[:, changed], changed)
    with np.errstate(invalid="ignore", divide="ignore"):
        sq = np.where(views, errors * errors, 0.0)
        error_px = np.sqrt(sq.sum(axis=0) / views.sum(axis=0))
    return X, error_px, views


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
