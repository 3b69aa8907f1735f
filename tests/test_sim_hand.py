"""The simulated hand, objects, motions and paint (rig.sim.shapes/objects/hand/motion)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from rig.sim import shapes
from rig.sim.hand import PALMAR_REGIONS, REGION_NAMES, SUBJECTS, make_hand
from rig.sim.motion import HAND_POSES, KINDS, PAINT_DISTANCE_M, capsule_distance, make_motion
from rig.sim.objects import OBJECTS, PAINT_RGB, make_object

TABLE_TOP = -0.15
GRASP_S = 4.0


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


def test_ray_capsules_nearest_hit_in_blocks(monkeypatch):
    hand = make_hand()
    a, b, r = hand.capsules(np.zeros(26))
    monkeypatch.setattr(shapes, "_BLOCK", 256)            # several blocks with few rays
    o, d = rays_towards(np.array([0.0, 0.09, 0.0]), 1000, 0.1, seed=3)
    t, index, n = shapes.ray_capsules(o, d, a, b, r)
    check_hits(t, n, o, d, lambda p: shapes.sdf_capsules(p, a, b, r)[0])
    hit = np.isfinite(t)
    p = o[hit] + t[hit, None] * d[hit]
    own = shapes.capsule_distances(p, a, b, r)[np.arange(hit.sum()), index[hit]]
    np.testing.assert_allclose(own, 0.0, atol=1e-9)       # the reported capsule is the one hit
    assert np.all(index[~hit] == -1)
    # float32 rays from one broadcast camera centre, as a renderer passes them
    o32 = np.broadcast_to(np.array([0.5, -0.4, 0.3], np.float32), d.shape)
    t32, _, n32 = shapes.ray_capsules(o32, (np.array([0.0, 0.09, 0.0]) - o32 + 0.05 * np.sin(d)).astype(np.float32), a, b, r)
    assert t32.dtype == np.float32 and n32.dtype == np.float32 and np.isfinite(t32).any()


def test_signed_distances():
    lo, hi = np.array([-1.0, -2.0, -3.0]), np.array([1.0, 2.0, 3.0])
    p = np.array([[0, 0, 0], [2, 0, 0], [2, 3, 0], [0.5, 0, 0]], float)
    np.testing.assert_allclose(shapes.sdf_box(p, lo, hi), [-1, 1, np.sqrt(2), -0.5])
    p = np.array([[0, 0, 0], [3, 0, 0], [3, 0, 2], [0, 0, 1.5], [0.5, 0, 0]])
    np.testing.assert_allclose(shapes.sdf_cylinder(p, 1.0, -1.0, 1.0), [-1, 2, np.sqrt(5), 0.5, -0.5])
    a = np.array([[0, 0, 0], [1, 0, 0.0]])
    b = np.array([[0, 0, 1], [1, 0, 1.0]])
    dist, idx = shapes.sdf_capsules(np.array([[0.5, 0, 0.5], [-1, 0, 2], [1.2, 0, 0.5]]), a, b, np.array([0.1, 0.3]))
    np.testing.assert_allclose(dist, [0.2, np.sqrt(2) - 0.1, -0.1])
    np.testing.assert_array_equal(idx, [1, 0, 1])


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


# ----------------------------------------------------------------------------- hand model

@pytest.fixture(scope="module")
def hand():
    return make_hand("s01")


def test_surface_points_cover_the_outer_capsule_surface(hand):
    assert 4000 < hand.n_points < 15000
    a, b, r = hand.capsules(np.zeros(26))
    dist, _ = shapes.sdf_capsules(hand.surface_rest, a, b, r)
    np.testing.assert_allclose(dist, 0.0, atol=1e-4)          # on the union's outer surface
    spacing, _ = cKDTree(hand.surface_rest).query(hand.surface_rest, k=2)
    assert 0.0015 < np.median(spacing[:, 1]) < 0.003
    # posed points stay on their own capsule, with its outward normal
    angles = np.r_[0.3, -1.0, 0.5, 0.05, 0.0, -0.02, np.linspace(-0.1, 1.4, 20)]
    angles = hand.skeleton.clamp(angles)
    pts, nrm = hand.surface_points(angles)
    a, b, r = hand.capsules(angles)
    own = shapes.capsule_distances(pts, a, b, r)[np.arange(hand.n_points), hand.surface_capsule]
    np.testing.assert_allclose(own, 0.0, atol=1e-9)
    bumped = shapes.capsule_distances(pts + 1e-4 * nrm, a, b, r)[np.arange(hand.n_points), hand.surface_capsule]
    np.testing.assert_allclose(bumped, 1e-4, atol=1e-9)
    batch, _ = hand.surface_points(np.stack([np.zeros(26), angles]))
    np.testing.assert_allclose(batch[1], pts)


def test_hand_dimensions_are_realistic(hand):
    # Palm ~2.5 cm thick: a vertical ray through the middle of the palm.
    a, b, r = hand.capsules(np.zeros(26))
    x, y = hand.skeleton.rest_joints()[9, :2] * [1.0, 0.55]
    down = shapes.ray_capsules(np.array([[x, y, 1.0]]), np.array([[0, 0, -1.0]]), a, b, r)[0][0]
    up = shapes.ray_capsules(np.array([[x, y, -1.0]]), np.array([[0, 0, 1.0]]), a, b, r)[0][0]
    assert 0.022 < 2.0 - down - up < 0.028
    fingers = hand.capsule_finger >= 1
    radii = hand.capsule_radius[fingers].reshape(4, 3)
    assert np.all(np.diff(radii, axis=1) < 0) and np.all(radii[:, 0] <= 0.0105) and np.all(radii[:, 2] >= 0.0065)
    assert hand.skin_albedo.shape == (3,) and np.all((hand.skin_albedo > 0) & (hand.skin_albedo < 1))
    counts = np.bincount(hand.surface_region, minlength=len(REGION_NAMES))
    assert np.all(counts > 0)                                 # every region is sampled


def test_subjects_differ_in_size_and_proportion():
    assert len(SUBJECTS) >= 3
    lengths = []
    for name in SUBJECTS:
        rest = make_hand(name).skeleton.rest_joints()
        palm = np.linalg.norm(rest[9] - rest[0])
        finger = np.linalg.norm(rest[12] - rest[9])
        lengths.append((palm + finger, finger / palm))
    lengths = np.array(lengths)
    assert np.ptp(lengths[:, 0]) > 0.02 and np.ptp(lengths[:, 1]) > 0.05
    with pytest.raises(ValueError, match="s01, s02, s03"):
        make_hand("s99")


def test_subjects_differ_in_girth_beyond_their_size():
    """A subject's flesh is SUBJECT_GIRTH times as thick as the average hand of the same bones."""
    from rig.sim.hand import SUBJECT_GIRTH, HandModel

    for name in SUBJECTS:
        subject = make_hand(name)
        average = HandModel(subject.skeleton)
        assert np.allclose(subject.capsule_radius, SUBJECT_GIRTH[name] * average.capsule_radius)
        assert np.allclose(subject.capsule_rest_a, average.capsule_rest_a)
    assert max(SUBJECT_GIRTH.values()) - min(SUBJECT_GIRTH.values()) >= 0.15


def test_albedo_is_paint_only_where_painted(hand):
    pts, _ = hand.surface_points(np.zeros(26))
    paint = np.zeros(hand.n_points, bool)
    paint[:100] = True
    rgb = hand.albedo(pts + 1e-4, np.zeros(26), paint)
    np.testing.assert_allclose(rgb[:100], np.tile(PAINT_RGB, (100, 1)), atol=1e-6)
    np.testing.assert_allclose(rgb[200:], np.tile(hand.skin_albedo, (hand.n_points - 200, 1)), atol=1e-6)


# ----------------------------------------------------------------------------- motions

@pytest.fixture(scope="module")
def grasps(hand):
    return {name: make_motion("grasp", hand, make_object(name, painted=True), GRASP_S, seed=0)
            for name in OBJECTS}


@pytest.mark.parametrize("name", OBJECTS)
def test_grasp_touches_without_interpenetration(hand, grasps, name):
    motion = grasps[name]
    pose = motion.object_poses(np.zeros(1))
    pose = (pose[0][0], pose[1][0])

    def sdf(x):
        return motion.obj.sdf(x, pose)

    t = np.arange(0.0, GRASP_S + 1e-9, 0.01)
    a, b, r = hand.capsules(motion.hand_angles(t))
    dist = capsule_distance(a, b, r, sdf, samples=96)        # denser than the search used
    assert dist.min() > -0.001                               # never deeper than 1 mm
    assert np.all(np.minimum(a[..., 2], b[..., 2]) - r > TABLE_TOP - 1e-4)    # above the table
    hold = (t > 0.41 * GRASP_S) & (t < 0.61 * GRASP_S)
    assert dist[hold].min() < 0.001                          # contact during the hold
    at_hold = dist[np.flatnonzero(hold)[0]]
    touching = {f for f in range(5) if at_hold[hand.capsule_finger == f].min() < 0.001}
    assert len(touching) >= 3 and 0 in touching             # thumb and at least two fingers
    assert 0.001 < at_hold[hand.capsule_finger < 0].min() < 0.004   # palm a few mm away
    # Surface points agree: the closest skin point is within 1 mm at the hold.
    pts, _ = hand.surface_points(motion.hand_angles(t[hold][:1]))
    assert -0.001 < sdf(pts[0]).min() < 0.001
    # Approach from above and retreat: no contact at the start and end.
    assert dist[0].min() > 0.05 and dist[-1].min() > 0.05


@pytest.mark.parametrize("name", OBJECTS)
def test_paint_lies_on_the_grasping_surfaces_facing_the_object(hand, grasps, name):
    motion = grasps[name]
    paint = motion.contact_accumulated()
    assert paint.sum() > 100
    regions = hand.surface_region[paint]
    assert np.isin(regions, PALMAR_REGIONS).mean() > 0.9
    names = {REGION_NAMES[k] for k in regions}
    assert "palm" in names and not names & {"back", "wrist"}
    fingers = {n.split("_")[0] for n in names} - {"palm"}
    assert "thumb" in fingers and len(fingers) >= 3
    # At the moment each point got its paint it was within 4 mm and faced the object.
    first = motion.first_contact_s[paint]
    pose = (motion.object_poses(np.zeros(1))[0][0], motion.object_poses(np.zeros(1))[1][0])
    facings = []
    for t0 in np.unique(first):
        idx = np.flatnonzero(paint)[first == t0]
        pts, nrm = hand.surface_points(motion.hand_angles(np.array([t0])))
        p, n = pts[0, idx], nrm[0, idx]
        assert np.all(motion.obj.sdf(p, pose) < PAINT_DISTANCE_M)
        facing = np.sum(n * -motion.obj.normal(p, pose), axis=1)
        facings.append(facing)
    facings = np.concatenate(facings)
    # Along a box edge a capsule's flank can lie in the band side-on; none faces away.
    assert np.all(facings > -0.25) and np.mean(facings > 0) > 0.97


def test_paint_accumulates_and_stays(hand, grasps):
    motion = grasps["mug"]
    t = np.linspace(0, GRASP_S, 9)
    acc = [motion.contact_accumulated(x) for x in t]
    assert not acc[0].any()
    for before, after in zip(acc, acc[1:]):
        assert np.all(after >= before)
    instant = motion.contact_instant(t)
    assert instant[4].any() and not instant[-1].any()        # touching at the hold, not after
    assert np.all(acc[-1] >= instant.any(axis=0))
    np.testing.assert_array_equal(motion.state(GRASP_S).paint, acc[-1])
    np.testing.assert_array_equal(motion.state(0.3 * GRASP_S).paint, motion.contact_accumulated(0.3 * GRASP_S))
    # The contact set is a property of the path, not of the take's duration.
    longer = make_motion("grasp", hand, make_object("mug", painted=True), 2.5 * GRASP_S, seed=0)
    assert (longer.contact_accumulated() != acc[-1]).sum() <= 0.02 * acc[-1].sum()
    # An unpainted object still has contact, but leaves no paint.
    plain = make_motion("grasp", hand, make_object("mug"), GRASP_S, seed=0)
    assert not plain.state(GRASP_S).paint.any() and plain.contact_accumulated().sum() == acc[-1].sum()


def test_canonical_shows_the_grasp_paint_to_the_cameras(hand, grasps):
    obj = make_object("box", painted=True)
    motion = make_motion("canonical", hand, obj, 2.0, seed=0)
    first, last = motion.state(0.0), motion.state(2.0)
    np.testing.assert_array_equal(first.hand_angles, last.hand_angles)        # still
    assert first.object_pose is None
    np.testing.assert_array_equal(first.paint, grasps["box"].contact_accumulated())
    angles = first.hand_angles
    np.testing.assert_allclose(angles[6:][1::4][[0, 2]], 0.0)                 # thumb, middle flat
    assert np.all(np.abs(angles[6:].reshape(5, 4)[:, [0, 2, 3]]) < 1e-12)     # no flexion
    _, nrm = hand.surface_points(angles)
    palm = hand.surface_region == REGION_NAMES.index("palm")
    assert np.median(nrm[palm, 2]) > 0.7                                      # palm up
    assert np.mean(nrm[first.paint, 2] > 0) > 0.8                             # paint faces the ceiling
    a, b, r = hand.capsules(angles)
    assert np.all(np.minimum(a[:, 2], b[:, 2]) - r > TABLE_TOP + 0.02)
    unpainted = make_motion("canonical", hand, None, 2.0)
    assert not unpainted.state(1.0).paint.any()


def test_hand_routine_visits_twenty_distinct_poses(hand):
    duration = 30.0
    motion = make_motion("hand", hand, None, duration, seed=3)
    assert motion.object_poses(np.zeros(1)) is None and motion.state(1.0).object_pose is None
    t = np.arange(0.0, duration, 0.005)
    angles = motion.hand_angles(t)
    assert np.all(hand.skeleton.within_limits(angles))
    # Holds are where nothing moves; each hold is one pose.
    still = np.r_[True, np.all(np.abs(np.diff(angles, axis=0)) < 1e-12, axis=1)]
    starts = np.flatnonzero(still & ~np.r_[False, still[:-1]])
    poses = angles[starts, 6:]
    distinct = [poses[0]]
    for p in poses[1:]:
        if min(np.abs(p - q).max() for q in distinct) > 0.25:
            distinct.append(p)
    assert len(distinct) >= 18 and len(HAND_POSES) >= 20
    # Varied global orientation; the hand stays above the table and inside the cube.
    rot = angles[starts, :3]
    assert np.ptp(rot, axis=0).max() > 1.0
    a, b, r = hand.capsules(angles[::10])
    assert (np.minimum(a[..., 2], b[..., 2]) - r).min() > TABLE_TOP + 0.01
    assert np.abs(np.concatenate([a, b])).max() < 0.45
    assert np.array_equal(angles, make_motion("hand", hand, None, duration, seed=3).hand_angles(t))
    assert not np.array_equal(angles, make_motion("hand", hand, None, duration, seed=4).hand_angles(t))


@pytest.mark.parametrize("kind", ["hand", "grasp"])
def test_motions_are_continuous_and_humanly_fast(hand, grasps, kind):
    motion = grasps["sphere"] if kind == "grasp" else make_motion("hand", hand, None, 30.0, seed=0)
    t = np.sort(np.random.default_rng(5).uniform(0, motion.duration_s, 4000))
    a = motion.hand_angles(t)
    assert np.abs(motion.hand_angles(t + 1e-7) - a).max() < 1e-5       # no jump anywhere
    dt = 1e-3
    b = motion.hand_angles(t + dt)
    assert np.abs(b - a).max() / dt < 10.0                              # rad/s
    speed = np.linalg.norm(hand.skeleton.forward(b) - hand.skeleton.forward(a), axis=-1) / dt
    assert speed.max() < 1.0                                            # m/s
    np.testing.assert_array_equal(motion.hand_angles(np.array([-1.0])), motion.hand_angles(np.array([0.0])))


def test_calibration_and_object_motions():
    calib = make_motion("calibration", None, None, 1.0)
    state = calib.state(0.5)
    assert state.hand_angles is None and state.object_pose is None and state.paint is None
    assert calib.hand_angles(np.zeros(3)) is None
    obj = make_object("sphere")
    still = make_motion("object", None, obj, 1.0)
    r, t = still.object_poses(np.linspace(0, 1, 5))
    assert r.shape == (5, 3, 3) and np.all(t == obj.resting_pose(TABLE_TOP)[1])
    assert still.state(0.2).hand_angles is None


def test_make_motion_rejects_bad_requests(hand):
    with pytest.raises(ValueError, match=", ".join(KINDS)):
        make_motion("dance", hand, None, 1.0)
    with pytest.raises(ValueError, match="object"):
        make_motion("grasp", hand, None, 1.0)
    with pytest.raises(ValueError, match="hand"):
        make_motion("hand", None, None, 1.0)
