"""The simulated hand, its motions and paint (rig.sim.anatomy/skin/hand/motion)."""

from __future__ import annotations

import numpy as np
import pytest
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh

from manus_core.ground_truth import LABEL_HAND, LABEL_PAINT
from manus_core.skeleton import REST_FRAMES
from rig.layouts import make_rig
from rig.sim.anatomy import HandShape, RestHand
from rig.sim.cube import true_cameras
from rig.sim.hand import PALMAR_REGIONS, REGION_NAMES, SUBJECTS, TOUCH_M, make_hand
from rig.sim.motion import HAND_POSES, KINDS, PRESS_DEPTH_M, make_motion
from rig.sim.objects import OBJECTS, PAINT_RGB, make_object
from rig.sim.skin import SPACING_M

TABLE_TOP = -0.15
GRASP_S = 4.0

# ----------------------------------------------------------------------------- hand model

POSE = np.r_[0.3, -1.0, 0.5, 0.05, 0.0, -0.02, np.linspace(-0.1, 1.4, 20)]


@pytest.fixture(scope="module")
def hand():
    return make_hand("s01")


def cast(vertices, faces, o, d):
    """Nearest hit t (N,) of unit rays on a triangle mesh (embree, either side), inf on a miss."""
    scene = rtcs.EmbreeScene()
    TriangleMesh(scene, vertices.astype(np.float32), faces.astype(np.int32))
    o, d = np.broadcast_arrays(np.float32(o).reshape(-1, 3), np.float32(d).reshape(-1, 3))
    t = scene.run(o.copy(), d.copy(), output=1)["tfar"].astype(np.float64)
    return np.where(t < 1e30, t, np.inf)


def exit_distance(sdf, o, d, step=2e-4):
    """How far (N,) unit rays from points inside the solid of `sdf` go before they leave it."""
    t = np.arange(0.0, 0.06, step)
    inside = sdf((o[:, None] + t[:, None] * d[:, None]).reshape(-1, 3)).reshape(len(o), len(t)) < 0
    assert inside[:, 0].all() and not inside.all(axis=1).any()
    lo = t[inside.argmin(axis=1) - 1]
    for h in step / 2 ** np.arange(1, 30):
        lo = np.where(sdf(o + (lo + h)[:, None] * d) < 0, lo + h, lo)
    return lo


def sections(rest):
    """Centres (5,3,3) of sections through finger segments (tip pads 62 % along), directions (5,4,3)."""
    j = rest.joints
    centre = np.array([[j[4 * f + k + 1] + (0.62 if k == 2 else 0.5) * (j[4 * f + k + 2] - j[4 * f + k + 1])
                        for k in range(3)] for f in range(5)])
    x, z = REST_FRAMES[:, :, 0], REST_FRAMES[:, :, 2]
    return centre, np.stack([x, -x, z, -z], axis=1)


def vertex_area(hand):
    """Skin area (V,) (m^2) of each rest vertex: a third of each triangle around it."""
    v, f = hand.surface_rest, hand.faces
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    return np.bincount(f.ravel(), np.repeat(area / 3, 3), len(v))


def palm_centre(rest):
    """On the palm's mid-plane, across from the middle of the knuckles, 55 % of the way up."""
    return np.array([rest.joints[[5, 9, 13, 17], 0].mean(), 0.55 * rest.joints[9, 1], 0.0])


@pytest.mark.parametrize("name", SUBJECTS)
def test_rest_skin_is_the_zero_level_of_the_anatomy(name):
    hand = make_hand(name)
    v, sdf = hand.surface_rest, hand.rest.sdf
    edges = np.sort(hand.faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    assert np.all(np.unique(edges, axis=0, return_counts=True)[1] == 2)      # closed, no tears
    assert 0.8 < np.median(np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1)) / SPACING_M < 1.2
    # Marching cubes interpolates linearly along grid edges h long: a chord of flesh curved over
    # R sags by h^2 / 8R, 0.1 h^2/mm for the ~1.25 mm fillets (0.07 h^2/mm seen for 99.9 % of the
    # skin at h = 1.25 and 2 mm); the worst, at the palm's corners by the wrist, 0.2 h seen.
    dist, h_mm = np.abs(sdf(v)), SPACING_M * 1000
    assert dist.max() < 0.25 * SPACING_M and np.mean(dist < 1e-4 * h_mm ** 2) > 0.999
    grad = np.stack([sdf(v + e) - sdf(v - e) for e in np.eye(3) * 1e-5], axis=1)
    cos = np.sum(grad / np.linalg.norm(grad, axis=1, keepdims=True) * hand.surface_normal_rest, axis=1)
    angle = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    # The normals are the grid's gradient: off where the field bends within a cell, ~h/R (fillets,
    # webs, the small s02's pads; at h = 1.25 mm the mesh's own facets are off more).
    assert np.median(angle) < 1.5 * h_mm and np.mean(angle < 12 * h_mm) > 0.99   # 1.1 h; 99.2 % seen
    assert np.all(np.bincount(hand.surface_region, minlength=len(REGION_NAMES)) > 0)   # every region


def test_posed_skin_is_the_linear_blend_of_its_bones_and_painted_where_asked(hand):
    w = hand.weights.astype(np.float64)
    assert np.all(w >= 0) and np.all((w > 0).sum(axis=1) <= 4) and np.allclose(w.sum(axis=1), 1.0, atol=1e-6)
    np.testing.assert_array_equal(hand.surface_bone, w.argmax(axis=1))
    angles = hand.skeleton.clamp(POSE)
    rot, trans = hand.skeleton.bone_transforms(angles)
    ref_n = np.einsum("vb,bij,vj->vi", w, rot, hand.surface_normal_rest)
    pts, nrm = hand.surface_points(angles)
    # blended in float32: coordinates of ~0.2 m round by ~1e-8 m, while a wrong weight moves mm
    np.testing.assert_allclose(pts, np.einsum("vb,bij,vj->vi", w, rot, hand.surface_rest) + w @ trans, atol=1e-6)
    np.testing.assert_allclose(nrm, ref_n / np.linalg.norm(ref_n, axis=1, keepdims=True), atol=1e-5)
    np.testing.assert_allclose(hand.surface_points(np.zeros(26))[0], hand.surface_rest, atol=1e-6)
    batch, batch_n = hand.surface_points(np.stack([np.zeros(26), angles]))
    np.testing.assert_allclose(batch[1], pts, atol=1e-9)
    np.testing.assert_allclose(batch_n[1], nrm, atol=1e-7)
    idx = np.arange(0, hand.n_points, 7)
    sub, none = hand.surface_points(angles, idx, normals=False)
    assert none is None and np.allclose(sub, pts[idx], rtol=0, atol=1e-9)
    # posed_mesh: the same skin, PAINT_RGB and LABEL_PAINT exactly where painted, the skin elsewhere
    before, paint = hand.vertex_albedo.copy(), np.random.default_rng(6).random(hand.n_points) < 0.1
    mesh = hand.posed_mesh(angles, paint)
    assert np.array_equal(mesh.vertices, pts) and np.array_equal(mesh.normals, nrm)
    assert np.array_equal(mesh.faces, hand.faces) and mesh.albedo.dtype == np.float32
    np.testing.assert_array_equal(mesh.albedo, np.where(paint[:, None], PAINT_RGB.astype(np.float32), before))
    np.testing.assert_array_equal(mesh.label, np.where(paint, LABEL_PAINT, LABEL_HAND))
    np.testing.assert_array_equal(hand.vertex_albedo, before)                 # a copy was painted
    plain = hand.posed_mesh(angles)
    assert np.array_equal(plain.albedo, before) and np.all(plain.label == LABEL_HAND)


def test_hand_dimensions_are_realistic(hand):
    v, faces, c = hand.surface_rest, hand.faces, palm_centre(hand.rest)
    # Across the palm at its centre, the height of the palmar skin (rays cast up from below).
    xs = c[0] + np.arange(-0.045, 0.0451, 0.005)
    z = cast(v, faces, np.c_[xs, np.full(len(xs), c[1]), np.full(len(xs), -1.0)], [0, 0, 1.0]) - 1.0
    thickness = 1.0 - cast(v, faces, c + [0, 0, 1.0], [0, 0, -1.0])[0] - z[9]
    assert 0.020 < thickness < 0.040                            # an adult's palm, hollow included
    # The hollow: the palmar skin is highest mid-palm; the thenar (radial) and hypothenar (ulnar)
    # eminences bulge at least 3 mm lower (12 and 5 mm seen).
    assert z[8:11].max() == z[np.isfinite(z)].max()
    assert z[xs < c[0] - 0.015].min() < z[9] - 0.003 > z[xs > c[0] + 0.015].min()
    # Finger cross-sections, cast from each segment's axis outwards.
    centre, dirs = sections(hand.rest)
    t = cast(v, faces, np.repeat(centre, 4, axis=1), np.repeat(dirs[:, None], 3, axis=1)).reshape(5, 3, 4)
    width = t[..., 0] + t[..., 1]
    assert 0.014 < width[1, 0] < 0.021                          # an index proximal phalanx (16.4 mm)
    assert np.all(np.diff(width[1:], axis=1) < 0)               # fingers taper towards the tip
    # Fingertip pads: the pulp reaches 1.5x as far palmar as the nail side dorsal (1.8x seen; the
    # bare elliptical section without its pad has 0.80 / 0.66 = 1.2).
    assert np.all(t[:, 2, 3] > 1.5 * t[:, 2, 2])
    # Skin area, wrist stub included: a hand is ~2.5 % of an adult's 1.8 m^2 (425 cm^2 seen).
    assert 0.03 < vertex_area(hand).sum() < 0.055
    assert hand.skin_albedo.shape == (3,) and np.all((hand.skin_albedo > 0) & (hand.skin_albedo < 1))


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


def flesh(rest):
    """Widths (4,2) of the middle and distal phalanges, fingertip palmar / dorsal (4,), palm
    thickness and width at its centre, of the four fingers, measured on the SDF."""
    centre, dirs = sections(rest)
    t = exit_distance(rest.sdf, np.repeat(centre[1:, 1:], 4, axis=1).reshape(-1, 3),
                      np.repeat(dirs[1:, None], 2, axis=1).reshape(-1, 3)).reshape(4, 2, 4)
    palm = exit_distance(rest.sdf, np.tile(palm_centre(rest), (4, 1)), np.r_[np.eye(3)[[2, 0]], -np.eye(3)[[2, 0]]])
    return t[..., 0] + t[..., 1], t[:, 1, 3] / t[:, 1, 2], palm[0] + palm[2], palm[1] + palm[3]


def test_subjects_differ_in_flesh_beyond_their_size():
    """Against the average flesh on the same bones, a subject's fingers are finger_thickness times
    as wide, its palm palm_thickness times as thick and palm_width times as wide, its pads fuller
    or flatter by pad_fullness: what a template that knows only the bones misses."""
    subjects = [s for s in SUBJECTS.values() if s.name != "s01"]
    assert np.ptp([s.finger_thickness for s in subjects]) >= 0.15 and np.ptp([s.pad_fullness for s in subjects]) >= 0.5
    for shape in subjects:
        subject = flesh(make_hand(shape.name).rest)
        average = flesh(RestHand(HandShape(shape.name, shape.bone_lengths)))
        # fingers scale exactly but for their fixed 2.5 mm fillets and 0.6 mm creases (0.5 % seen)
        np.testing.assert_allclose(subject[0] / average[0], shape.finger_thickness, rtol=0.02)
        # the palm's hollow and the thenar keep the size the bones give them (2 % seen)
        assert abs(subject[2] / average[2] / shape.palm_thickness - 1) < 0.04
        assert abs(subject[3] / average[3] / shape.palm_width - 1) < 0.04
        # the fingertip's palmar / dorsal, 1.83 on average, follows the pads (1.68 for s02, 2.05 for s03)
        assert np.all((subject[1] - average[1]) * np.sign(shape.pad_fullness - 1) > 0.05)


def test_vertex_albedo_has_nails_and_darker_creases(hand):
    albedo, normal = hand.vertex_albedo, hand.surface_normal_rest
    nail = np.all(albedo == np.float32(hand.shape.nail_rgb), axis=1)
    assert albedo.dtype == np.float32 and albedo.shape == (hand.n_points, 3)
    area = vertex_area(hand)
    for f in range(5):                          # 1.3-2.4 cm^2 each seen, on the back of the finger
        on = nail & (hand.surface_bone == 4 * f + 3)
        assert 6e-5 < area[on].sum() < 3e-4 and np.all(normal[on] @ REST_FRAMES[f][:, 2] > 0.25)
    assert not np.any(nail & (hand.surface_bone % 4 != 3))
    assert all(REGION_NAMES[k].endswith(("_dorsal", "_tip")) for k in np.unique(hand.surface_region[nail]))
    assert 0.9 < np.median(albedo[~nail] / hand.skin_albedo) < 1.1
    lum, depth = albedo @ np.array([0.3, 0.59, 0.11]), hand.rest.crease_depth(hand.surface_rest)
    crease, plain = ~nail & (depth > 0.5), ~nail & hand.surface_palmar & (depth < 0.05)
    assert area[crease].sum() > 1e-4 and lum[crease].mean() < 0.85 * lum[plain].mean()    # 0.7x seen


# ----------------------------------------------------------------------------- motions

@pytest.fixture(scope="module")
def grasps(hand):
    return {name: make_motion("grasp", hand, make_object(name, painted=True), GRASP_S, seed=0)
            for name in OBJECTS}


def object_pose(motion):
    r, t = motion.object_poses(np.zeros(1))
    return r[0], t[0]


@pytest.fixture(scope="module")
def tracks(hand, grasps):
    """Per object: times (T,) every 20 ms of the grasp and per frame the least signed distance
    from the object of the unpressed (blended) skin of the palm and of each finger (T,6)."""
    group = np.where(hand.surface_bone % 4 == 0, 0, 1 + hand.surface_bone // 4)
    t, out = np.linspace(0.0, GRASP_S, 201), {}
    for name, motion in grasps.items():
        gaps = [motion.obj.sdf(hand.surface_points(a, normals=False)[0], object_pose(motion))
                for a in np.array_split(motion.hand_angles(t), 8)]
        out[name] = t, np.concatenate([np.stack([d[:, group == g].min(axis=1) for g in range(6)], 1) for d in gaps])
    return out


@pytest.mark.parametrize("name", OBJECTS)
def test_grasp_presses_the_finger_pads_into_the_object_and_the_skin_flattens(hand, grasps, tracks, name):
    motion, (t, gaps) = grasps[name], tracks[name]
    # Planning presses a 2 mm proxy of the skin PRESS_DEPTH_M deep: the full mesh between those
    # vertices may go deeper, by 1 mm at most (0.2-0.5 mm seen).
    assert gaps.min() > -PRESS_DEPTH_M - 0.001
    hold = np.flatnonzero((t > 0.41 * GRASP_S) & (t < 0.61 * GRASP_S))
    touching = np.flatnonzero(gaps[hold[0], 1:] < TOUCH_M)
    assert len(touching) >= 3 and 0 in touching                 # thumb and at least two fingers
    assert np.all(gaps[hold][:, 1 + touching] < -0.0005)        # pressed all along the hold
    assert np.all((gaps[hold, 0] > 0.001) & (gaps[hold, 0] < 0.004))      # palm a few mm away
    assert gaps[0].min() > 0.05 and gaps[-1].min() > 0.05      # approach from above, retreat
    pts, _ = hand.surface_points(motion.hand_angles(t[hold]), normals=False)
    assert pts[..., 2].min() > TABLE_TOP - 1e-4                 # above the table
    # contact() culls with bone-bound clusters: it finds every touching vertex all the same
    frame, vertex = hand.contact(motion.hand_angles(t[hold[:1]]), motion.obj, object_pose(motion))
    touch = motion.obj.sdf(pts[0], object_pose(motion)) < TOUCH_M
    assert np.all(frame == 0) and np.array_equal(np.sort(vertex), np.flatnonzero(touch))
    # Rendered (posed_mesh), the skin that entered the object moves out onto it and faces it.
    inside, facing, pose = [], [], object_pose(motion)
    for a in motion.hand_angles(t[gaps[:, 1:].min(axis=1) < 0]):
        v, _ = hand.surface_points(a, normals=False)
        d, mesh = motion.obj.sdf(v, pose), hand.posed_mesh(a, obj=motion.obj, object_pose=pose)
        moved = np.any(mesh.vertices != v, axis=1)
        assert np.all(moved[d < 0]) and not np.any(moved[d > 1e-4])         # only skin that entered
        # out by its depth at least (+ a 20 um gap), the shortest way or a little more round an edge
        step = np.linalg.norm(mesh.vertices[moved] - v[moved], axis=1)
        assert np.all((step > -d[moved] - 1e-6) & (step < -1.5 * d[moved] + 5e-5))
        facing.append(np.sum(mesh.normals[moved] * motion.obj.normal(mesh.vertices[moved], pose), axis=1))
        inside.append(motion.obj.sdf(mesh.vertices, pose).min())
    facing = np.concatenate(facing)                             # 99.97 % within 8 deg seen
    assert np.all(facing < 0) and np.mean(facing < -0.99) > 0.99
    # no skin left inside the object, at a box's edge or the mug's rim either (where one step along
    # the gradient, the diagonal of two faces, stopped 0.3 mm short)
    assert min(inside) >= -1e-6


@pytest.mark.parametrize("name", OBJECTS)
def test_paint_lies_on_the_grasping_surfaces_facing_the_object(hand, grasps, name):
    motion, pose = grasps[name], object_pose(grasps[name])
    paint = motion.contact_accumulated()
    assert vertex_area(hand)[paint].sum() > 3e-4  # 3+ pressed pads of ~1 cm^2 (7-10 cm^2 seen)
    regions = hand.surface_region[paint]
    nail = np.all(hand.vertex_albedo[paint] == np.float32(hand.shape.nail_rgb), axis=1)
    assert np.isin(regions, PALMAR_REGIONS).mean() > 0.95 and nail.mean() < 0.01    # a nail's rim at most
    names = {REGION_NAMES[k] for k in regions}
    assert not names & {"back", "wrist", "palm"}                # the palm stays clear
    fingers = {n.split("_")[0] for n in names}
    assert "thumb" in fingers and len(fingers) >= 3
    # At the moment each vertex got its paint it touched the object and faced it.
    first, facings = motion.first_contact_s[paint], []
    for t0 in np.unique(first):
        pts, nrm = hand.surface_points(motion.hand_angles(np.array([t0])), np.flatnonzero(paint)[first == t0])
        assert np.all(motion.obj.sdf(pts[0], pose) < TOUCH_M)
        facings.append(np.sum(nrm[0] * -motion.obj.normal(pts[0], pose), axis=1))
    facings = np.concatenate(facings)
    # A fingertip rolled onto a box edge touches it side-on (0.4 deg past square seen); none faces away.
    assert np.all(facings > -0.1) and np.mean(facings > 0) > 0.99 and np.median(facings) > 0.7


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
    pts, nrm = hand.surface_points(angles)
    palm = hand.surface_region == REGION_NAMES.index("palm")
    assert np.median(nrm[palm, 2]) > 0.7                                      # palm up
    assert np.mean(nrm[first.paint, 2] > 0) > 0.8                             # paint faces the ceiling
    assert pts[:, 2].min() > TABLE_TOP + 0.02
    # 95 % of the paint in the image of 5+ cameras, facing them and not hidden by the hand (19+ seen).
    cams = true_cameras(make_rig("cube53", resolution=(320, 180), seed=0))
    target, normal = pts[first.paint], nrm[first.paint]
    uv = cams.project(target)
    seen = (uv >= 0).all(axis=2) & (uv < cams.size[:, None]).all(axis=2)
    for c, centre in enumerate(cams.centers):
        dist = np.linalg.norm(target - centre, axis=1)
        d = (target - centre) / dist[:, None]
        seen[c] &= (np.sum(normal * d, axis=1) < 0) & (cast(pts, hand.faces, centre, d) > dist - 5e-4)
    assert np.mean(seen.sum(axis=0) >= 5) > 0.95
    assert not make_motion("canonical", hand, None, 2.0).state(1.0).paint.any()


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
    pts, _ = hand.surface_points(angles[::20], normals=False)
    assert pts[..., 2].min() > TABLE_TOP + 0.01 and np.abs(pts).max() < 0.45
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
