"""The simulated cube's primitives and objects (rig.sim.shapes, rig.sim.objects)."""

from __future__ import annotations

import numpy as np
import pytest

from rig.sim import shapes
from rig.sim.objects import OBJECTS, PAINT_RGB, make_object

TABLE_TOP = -0.15


def sphere_trace(o, d, sdf, t_max=3.0, iters=300):
    """Independent reference for the analytic ray casts: march each ray by its SDF value."""
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    t = np.zeros(len(o))
    for _ in range(iters):
        step = sdf(o + t[:, None] * d)
        t = np.where(t < t_max, t + np.maximum(step, 0.0), t)
    return np.where(np.abs(sdf(o + t[:, None] * d)) < 1e-7, t, np.inf)


def rays_towards(centre, n, spread, seed):
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n, 3))
    o = centre + 0.6 * o / np.linalg.norm(o, axis=1, keepdims=True)
    d = centre + rng.uniform(-spread, spread, size=(n, 3)) - o
    return o, d * rng.uniform(0.5, 2.0, size=(n, 1))      # non-unit directions on purpose


def check_hits(t, normal, o, d, sdf):
    """Hit points lie on the surface, normals are the SDF gradient, t agrees with marching."""
    ref = sphere_trace(o, d, sdf) / np.linalg.norm(d, axis=1)
    assert np.array_equal(np.isfinite(t), np.isfinite(ref))
    hit = np.isfinite(t)
    assert 0.2 < hit.mean() < 0.95
    np.testing.assert_allclose(t[hit], ref[hit], atol=1e-6)
    p = o[hit] + t[hit, None] * d[hit]
    eps = 1e-6
    grad = np.stack([sdf(p + e) - sdf(p - e) for e in np.eye(3) * eps], axis=1) / (2 * eps)
    smooth = np.abs(np.linalg.norm(grad, axis=1) - 1) < 1e-3     # not within eps of a box edge
    assert smooth.mean() > 0.99
    np.testing.assert_allclose(normal[hit][smooth], grad[smooth], atol=1e-4)


# ----------------------------------------------------------------------------- shapes

def test_ray_primitives_agree_with_sphere_tracing():
    c = np.array([0.1, -0.05, 0.02])
    o, d = rays_towards(c, 2000, 0.08, seed=0)
    t = shapes.ray_sphere(o, d, c, 0.05)
    check_hits(t, (o + t[:, None] * d - c) / 0.05, o, d, lambda p: shapes.sdf_sphere(p, c, 0.05))
    lo, hi = np.array([-0.03, -0.02, -0.045]), np.array([0.03, 0.04, 0.045])
    o, d = rays_towards(np.zeros(3), 2000, 0.06, seed=1)
    t, n = shapes.ray_box(o, d, lo, hi)
    check_hits(t, n, o, d, lambda p: shapes.sdf_box(p, lo, hi))
    o, d = rays_towards(np.zeros(3), 2000, 0.06, seed=2)
    t, n = shapes.ray_cylinder(o, d, 0.04, -0.05, 0.05)
    check_hits(t, n, o, d, lambda p: shapes.sdf_cylinder(p, 0.04, -0.05, 0.05))


def test_signed_distances():
    lo, hi = np.array([-1.0, -2.0, -3.0]), np.array([1.0, 2.0, 3.0])
    p = np.array([[0, 0, 0], [2, 0, 0], [2, 3, 0], [0.5, 0, 0]], float)
    np.testing.assert_allclose(shapes.sdf_box(p, lo, hi), [-1, 1, np.sqrt(2), -0.5])
    p = np.array([[0, 0, 0], [3, 0, 0], [3, 0, 2], [0, 0, 1.5], [0.5, 0, 0]])
    np.testing.assert_allclose(shapes.sdf_cylinder(p, 1.0, -1.0, 1.0), [-1, 2, np.sqrt(5), 0.5, -0.5])


def test_posed_shapes_round_trip():
    rng = np.random.default_rng(4)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    pose = (q * np.sign(np.linalg.det(q)), np.array([0.1, 0.2, -0.3]))
    p = rng.normal(size=(10, 3))
    local = shapes.points_to_local(p, pose)
    np.testing.assert_allclose(local @ pose[0].T + pose[1], p, atol=1e-12)
    o, d = shapes.rays_to_local(p, p, pose)
    np.testing.assert_allclose(shapes.vectors_to_world(d, pose), p, atol=1e-12)


# ----------------------------------------------------------------------------- objects

@pytest.mark.parametrize("name", OBJECTS)
def test_objects_rest_on_the_table_and_are_textured(name):
    obj = make_object(name)
    pose = obj.resting_pose(TABLE_TOP)
    under = np.array([[0.0, 0.0, TABLE_TOP], [0.0, 0.0, TABLE_TOP - 0.001]])
    np.testing.assert_allclose(obj.sdf(under, pose), [0.0, 0.001], atol=1e-12)
    assert obj.radius >= obj.half_height
    # A grid of rays from above: the hit points are on the surface and on the object's top.
    g = np.linspace(-0.05, 0.05, 60)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    o = np.c_[xy, np.full(len(xy), 0.5)]
    d = np.tile([0.0, 0.0, -1.0], (len(o), 1))
    t, n, albedo = obj.intersect(o, d, pose)
    hit = np.isfinite(t)
    assert hit.mean() > 0.3 and albedo.dtype == np.float32
    np.testing.assert_allclose(obj.sdf(o[hit] + t[hit, None] * d[hit], pose), 0.0, atol=1e-9)
    assert np.all(n[hit, 2] > 0)                               # seen from above: facing up
    assert np.all(albedo[~hit] == 0)
    # Texture with detail (many distinct colours, strong contrast), not green.
    colours = albedo[hit]
    assert len(np.unique(colours.round(3), axis=0)) > 5 and colours.std(axis=0).max() > 0.1
    assert not np.all(colours[:, 1] > colours[:, 0])
    painted = make_object(name, painted=True).intersect(o, d, pose)[2][hit]
    assert np.all(painted[:, 1] > 2 * painted[:, 0]) and np.all(painted[:, 1] > 2 * painted[:, 2])
    np.testing.assert_allclose(painted.mean(axis=0), PAINT_RGB, atol=0.03)


def test_unknown_object_names_the_choices():
    with pytest.raises(ValueError, match="box, mug, sphere"):
        make_object("cup")
