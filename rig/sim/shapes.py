"""Vectorized ray casting and signed distances for the primitives of the simulated cube.

Rays are (o (N,3), d (N,3)); d need not be unit length and every returned t is the ray
parameter of o + t d. A miss is t = inf. Rays are assumed to start outside the solids (cameras
look at the scene from the walls); the nearest hit with t > 0 is returned. Signed distances are
negative inside. Float32 or float64 in, the same precision out.

Posed shapes: an object's pose (R (3,3), t (3,)) maps object coordinates to the world,
x_world = R @ x_local + t; `rays_to_local`, `points_to_local` and `vectors_to_world` move
between the two so that each primitive stays written in its own frame.
"""

from __future__ import annotations

import numpy as np

Pose = tuple[np.ndarray, np.ndarray]


def _float(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x)
    return x if x.dtype in (np.float32, np.float64) else x.astype(np.float64)


def points_to_local(p: np.ndarray, pose: Pose) -> np.ndarray:
    """World points (N,3) into the frame of a shape posed at (R, t)."""
    r, t = pose
    # einsum rather than @: numpy's matmul of (N,3) by (3,3) is an order of magnitude slower.
    return np.einsum("ni,ij->nj", np.asarray(p) - t, r)


def rays_to_local(o: np.ndarray, d: np.ndarray, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """World rays into a posed shape's frame; t values are unchanged by the rigid motion."""
    return points_to_local(o, pose), np.einsum("ni,ij->nj", np.asarray(d), pose[0])


def vectors_to_world(v: np.ndarray, pose: Pose) -> np.ndarray:
    """Directions or normals (N,3) from a posed shape's frame to the world."""
    return np.einsum("nj,ij->ni", np.asarray(v), pose[0])


def _nearest_positive(t: np.ndarray, axis: int = -1) -> tuple[np.ndarray, np.ndarray]:
    t = np.where(t > 0, t, np.inf)
    k = np.argmin(t, axis=axis)
    return np.take_along_axis(t, np.expand_dims(k, axis), axis).squeeze(axis), k


def _sphere_roots(oc: np.ndarray, d: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Nearer root of |oc + t d| = radius, inf on miss or behind; broadcasts over leading axes."""
    a = np.sum(d * d, axis=-1)
    b = np.sum(oc * d, axis=-1)
    c = np.sum(oc * oc, axis=-1) - radius * radius
    disc = b * b - a * c
    root = np.sqrt(np.maximum(disc, 0.0))
    t = (-b - root) / a
    return np.where((disc >= 0) & (t > 0), t, np.inf)


def ray_sphere(o: np.ndarray, d: np.ndarray, center: np.ndarray, radius: float) -> np.ndarray:
    """Nearest hit t (N,) of rays with a sphere; inf on miss."""
    o, d = _float(o), _float(d)
    return _sphere_roots(o - np.asarray(center, dtype=o.dtype), d, radius)


def ray_box(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned solid box [lo, hi]: (t (N,), outward normal (N,3)) by the slab method."""
    o, d = _float(o), _float(d)
    lo, hi = np.asarray(lo, dtype=o.dtype), np.asarray(hi, dtype=o.dtype)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1, t2 = (lo - o) * inv, (hi - o) * inv
    # A ray parallel to a slab and on its plane gives nan: count it as inside that slab.
    near = np.nan_to_num(np.minimum(t1, t2), nan=-np.inf)
    far = np.nan_to_num(np.maximum(t1, t2), nan=np.inf)
    axis = np.argmax(near, axis=1)
    t_near = np.take_along_axis(near, axis[:, None], 1)[:, 0]
    t_far = np.min(far, axis=1)
    hit = (t_near <= t_far) & (t_near > 0)
    t = np.where(hit, t_near, np.inf)
    normal = np.zeros((len(o), 3), dtype=o.dtype)
    rows = np.arange(len(o))
    normal[rows, axis] = np.where(hit, -np.sign(d[rows, axis]), 0.0)
    return t, normal


def ray_cylinder(o: np.ndarray, d: np.ndarray, radius: float, z0: float, z1: float) -> tuple[np.ndarray, np.ndarray]:
    """Solid cylinder of the local z axis between z0 and z1 with flat caps: (t (N,), normal (N,3))."""
    o, d = _float(o), _float(d)
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1]
    c = o[:, 0] ** 2 + o[:, 1] ** 2 - radius * radius
    disc = b * b - a * c
    with np.errstate(divide="ignore", invalid="ignore"):
        t_side = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
        z_side = o[:, 2] + t_side * d[:, 2]
        side_ok = (disc >= 0) & (a > 0) & (z_side >= z0) & (z_side <= z1)
        t_caps = (np.array([z0, z1], dtype=o.dtype) - o[:, 2:3]) / d[:, 2:3]
        p_caps = o[:, None, :2] + t_caps[..., None] * d[:, None, :2]
    caps_ok = np.isfinite(t_caps) & (np.sum(p_caps * p_caps, axis=-1) <= radius * radius)
    cand = np.stack([np.where(side_ok, t_side, np.inf), *np.where(caps_ok, t_caps, np.inf).T], axis=1)
    t, k = _nearest_positive(cand)
    hit_xy = o[:, :2] + np.where(np.isfinite(t), t, 0.0)[:, None] * d[:, :2]
    normal = np.zeros((len(o), 3), dtype=o.dtype)
    normal[:, :2] = np.where((k == 0)[:, None], hit_xy / radius, 0.0)
    normal[:, 2] = np.select([k == 1, k == 2], [-1.0, 1.0], 0.0)
    normal[~np.isfinite(t)] = 0.0
    return t, normal


def _norm3(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    # Component-wise: reductions over a trailing axis of length 3 are slow in numpy.
    return np.sqrt(x * x + y * y + z * z)


def sdf_sphere(p: np.ndarray, center: np.ndarray, radius: float) -> np.ndarray:
    """Signed distance (N,) to a sphere."""
    q = _float(p) - center
    return _norm3(q[..., 0], q[..., 1], q[..., 2]) - radius


def sdf_box(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Exact signed distance (N,) to the axis-aligned box [lo, hi]."""
    p = _float(p)
    lo, hi = np.asarray(lo, dtype=p.dtype), np.asarray(hi, dtype=p.dtype)
    q = np.abs(p - 0.5 * (lo + hi)) - 0.5 * (hi - lo)
    qx, qy, qz = q[..., 0], q[..., 1], q[..., 2]
    outside = _norm3(np.maximum(qx, 0.0), np.maximum(qy, 0.0), np.maximum(qz, 0.0))
    return outside + np.minimum(np.maximum(np.maximum(qx, qy), qz), 0.0)


def sdf_cylinder(p: np.ndarray, radius: float, z0: float, z1: float) -> np.ndarray:
    """Exact signed distance (N,) to the capped cylinder of the local z axis, z0 <= z <= z1."""
    p = _float(p)
    qr = np.hypot(p[..., 0], p[..., 1]) - radius
    qz = np.abs(p[..., 2] - 0.5 * (z0 + z1)) - 0.5 * (z1 - z0)
    return np.hypot(np.maximum(qr, 0.0), np.maximum(qz, 0.0)) + np.minimum(np.maximum(qr, qz), 0.0)
