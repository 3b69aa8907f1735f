"""Distorted pixels to undistorted normalized camera coordinates, batched over cameras and points.

A start from the series that inverts the radial model, then Newton steps on the full distortion
model (k1, k2, p1, p2, k3); an observation whose undistortion does not converge, or converges
beyond the polynomial's first fold, is NaN. Work runs in blocks of points small enough for their
temporaries to stay in the CPU cache.
"""

from __future__ import annotations

import functools

import numpy as np

from manus_core.cameras import CameraRig

# Elements (cameras x points) per block of the elementwise stages. A block's temporaries then stay
# in the CPU cache; whole-array temporaries of a large take are several times slower per element.
_BLOCK_ELEMENTS = 1 << 14


def point_blocks(n_cams: int, n_points: int) -> list[slice]:
    """Slices of the point axis, each about _BLOCK_ELEMENTS observations."""
    step = max(1, _BLOCK_ELEMENTS // max(n_cams, 1))
    return [slice(s, min(s + step, n_points)) for s in range(0, n_points, step)]


def _distortion_columns(rig: CameraRig) -> np.ndarray:
    """(k1, k2, p1, p2, k3) as (5,C,1): broadcasts against (C,n) blocks."""
    return rig.dist.T[:, :, None]


def _newton_delta(dist, x: np.ndarray, y: np.ndarray, tx: np.ndarray, ty: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The Newton update (dx, dy), to subtract, of distort(x, y) = (tx, ty) for any shape of x and y;
    dist = (k1, k2, p1, p2, k3), each broadcasting against x (per camera (C,1) or per observation (M,))."""
    k1, k2, p1, p2, k3 = dist
    xx, yy, xy_ = x * x, y * y, x * y
    r2 = xx + yy
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    d_radial = 2 * (k1 + r2 * (2 * k2 + 3 * k3 * r2))  # 2 d radial / d r2
    fx = x * radial + 2 * p1 * xy_ + p2 * (r2 + 2 * xx) - tx
    fy = y * radial + p1 * (r2 + 2 * yy) + 2 * p2 * xy_ - ty
    jxx = radial + xx * d_radial + 2 * p1 * y + 6 * p2 * x
    jyy = radial + yy * d_radial + 6 * p1 * y + 2 * p2 * x
    jxy = xy_ * d_radial + 2 * p1 * x + 2 * p2 * y  # the Jacobian is symmetric
    inv_det = 1.0 / (jxx * jyy - jxy * jxy)
    return (jyy * fx - jxy * fy) * inv_det, (jxx * fy - jxy * fx) * inv_det


def _invertible(dist, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Where the radial distortion r -> r radial(r^2) still increases at the undistorted point (x, y).

    Beyond its first fold the polynomial maps several radii to one, and a root found there is not
    the observation's ray.
    """
    k1, k2, _, _, k3 = dist
    r2 = x * x + y * y
    return 1 + r2 * (3 * k1 + r2 * (5 * k2 + 7 * k3 * r2)) > 0


# A Newton step smaller than this (normalized units, ~1e-4 px) leaves an error of its square.
_NEWTON_TOL = 1e-7
_NEWTON_STEPS = 8


def _inverse_radial_series(rig: CameraRig) -> tuple[np.ndarray, np.ndarray]:
    """Coefficients b (4,C,1) of the series r = r_d (1 + b1 s + b2 s^2 + b3 s^3 + b4 s^4), s = r_d^2,
    that inverts the radial model r_d = r (1 + k1 r^2 + k2 r^4 + k3 r^6) (series reversion, as in
    Drap and Lefevre 2016), and per camera the s (C,1) up to which it is a good start.

    Truncated, the series drifts off far from the centre (for strong pincushion lenses already in
    the image corners): beyond the radius where it is within 1e-3 of the true radius, or beyond
    the first fold, the distorted point itself is the better start.
    """
    return _series_for(rig.dist.tobytes())


@functools.lru_cache(maxsize=16)
def _series_for(dist_bytes: bytes) -> tuple[np.ndarray, np.ndarray]:
    # Cached on the coefficients: every block of every call with the same rig needs the same.
    k1, k2, _, _, k3 = np.frombuffer(dist_bytes).reshape(-1, 5).T[:, :, None]
    b = np.stack([-k1, 3 * k1 ** 2 - k2, -12 * k1 ** 3 + 8 * k1 * k2 - k3,
                  55 * k1 ** 4 - 55 * k1 ** 2 * k2 + 5 * k2 ** 2 + 10 * k1 * k3])
    r = np.linspace(0.0, 3.0, 301)
    r2 = r * r
    rd = r * (1 + r2 * (k1 + r2 * (k2 + r2 * k3)))  # (C,R)
    s = rd * rd
    start = rd * (1 + s * (b[0] + s * (b[1] + s * (b[2] + s * b[3]))))
    good = (np.abs(start - r) <= 1e-3 * r) & (1 + r2 * (3 * k1 + r2 * (5 * k2 + 7 * k3 * r2)) > 0)
    last = np.logical_and.accumulate(good, axis=1).sum(axis=1) - 1  # the first sample (r = 0) is good
    return b, s[np.arange(len(s)), last][:, None]


# When fewer than this share of a block's observations still move after a Newton step, the rest
# get their further steps one by one instead of the whole block another step.
_STRAGGLER_SHARE = 0.125


def undistort_columns(rig: CameraRig, px: np.ndarray, py: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distorted pixels px, py (C,n) to undistorted normalized coordinates x, y (C,n).

    K^-1, the inverse series of the radial model as the start (within 1e-7 of the answer over
    most of the image of a lens without tangential distortion; the distorted point itself where
    the series is no good), then Newton steps on the full
    model for the whole block while many observations still move, and for the few others one by
    one. NaN in, NaN out; an observation that does not converge, or converges beyond the first fold
    of the radial polynomial, is NaN.
    """
    dist = _distortion_columns(rig)
    (b1, b2, b3, b4), series_s = _inverse_radial_series(rig)
    K = rig.K
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        v = (py - K[:, 1, 2, None]) / K[:, 1, 1, None]
        u = (px - K[:, 0, 2, None] - K[:, 0, 1, None] * v) / K[:, 0, 0, None]
        s = u * u + v * v
        scale = np.where(s <= series_s, 1 + s * (b1 + s * (b2 + s * (b3 + s * b4))), 1.0)
        x, y = u * scale, v * scale
        for _ in range(_NEWTON_STEPS):
            dx, dy = _newton_delta(dist, x, y, u, v)
            x -= dx
            y -= dy
            moved = np.maximum(np.abs(dx), np.abs(dy))
            if np.count_nonzero(moved >= _NEWTON_TOL) <= _STRAGGLER_SHARE * moved.size:
                break
        cams, points = np.nonzero(moved >= _NEWTON_TOL)  # NaN compares False: missing stays missing
        if len(cams):  # the few that need more steps, one row per observation
            d = rig.dist[cams].T.copy()
            xs, ys, us, vs = x[cams, points], y[cams, points], u[cams, points], v[cams, points]
            active = np.arange(len(cams))
            for _ in range(_NEWTON_STEPS):
                dx, dy = _newton_delta(d[:, active], xs[active], ys[active], us[active], vs[active])
                xs[active] -= dx
                ys[active] -= dy
                active = active[~(np.maximum(np.abs(dx), np.abs(dy)) < _NEWTON_TOL)]
                if not len(active):
                    break
            xs[active] = ys[active] = np.nan
            x[cams, points], y[cams, points] = xs, ys
        bad = ~_invertible(dist, x, y)
    x[bad] = y[bad] = np.nan
    return x, y


def undistort_points(rig: CameraRig, pixels: np.ndarray) -> np.ndarray:
    """Distorted pixels (C,N,2) to undistorted normalized coordinates (C,N,2).

    NaN in, NaN out; an observation whose undistortion does not converge, or converges beyond the
    first fold of the distortion polynomial (far outside the image), is NaN as well.
    """
    pixels = np.asarray(pixels, dtype=np.float64)
    out = np.empty(pixels.shape)
    for b in point_blocks(*pixels.shape[:2]):
        out[:, b, 0], out[:, b, 1] = undistort_columns(rig, pixels[:, b, 0], pixels[:, b, 1])
    return out
