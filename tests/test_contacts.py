"""Contacts and their scoring, checked with the simulated hand's true geometry.

With the true surface of the hand (points rigidly on their bones) and points on the true object
surface standing in for the Gaussians, the contact code must reproduce the simulator's paint:
that is the upper bound the learned models are measured against in the end-to-end test.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from manus_capture.contacts import TAU_M, contact_value, hand_object_contacts, render_values, surface_value
from manus_capture.evaluate import canonical_pose, mask_scores, pick_views, score_contacts, spread_cameras
from manus_capture.template import PointHand, capsule_distances, capsule_template
from manus_core.errors import EvaluateError
from rig.layouts import make_rig
from rig.sim.cube import SimulatedCube
from rig.sim.skin import SPACING_M


def surface_samples(sdf, centre: np.ndarray, radius: float, n: int, seed: int = 0) -> np.ndarray:
    """Points on an SDF's zero set: random points near the object, pulled onto the surface."""
    rng = np.random.default_rng(seed)
    x = centre + rng.uniform(-radius, radius, (n, 3))
    h = 1e-5
    for _ in range(4):
        d = sdf(x)
        grad = np.stack([(sdf(x + h * e) - d) / h for e in np.eye(3)], axis=1)
        x = x - d[:, None] * grad / np.maximum(np.linalg.norm(grad, axis=1, keepdims=True), 1e-9)
    return x[np.abs(sdf(x)) < 1e-4]


@pytest.fixture(scope="module")
def scene():
    cfg = make_rig("cube53", cameras=20, resolution=(320, 180))
    cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, paint=True, object="mug"))
    grasp = SimulatedCube(cfg, "grasp", 2.0)
    canonical = SimulatedCube(cfg, "canonical", 2.0)
    pose = grasp.motion.object_poses(np.zeros(1))
    R, t = pose[0][0], pose[1][0]
    obj = surface_samples(lambda x: grasp.object.sdf(x, (R, t)), t, grasp.object.radius + 0.01, 200_000)
    times = np.linspace(0.0, 2.0, 121)
    return {"cfg": cfg, "grasp": grasp, "canonical": canonical, "object": obj, "truth_hand": SkinHand(grasp.hand),
            "angles": grasp.motion.hand_angles(times), "times": times, "pose": (R, t)}


class SkinHand(PointHand):
    """The simulated skin's vertices as the point model that the contact code scores, posed by the
    simulator's own blend skinning: the true hand."""

    def __init__(self, hand) -> None:
        super().__init__(hand.skeleton, hand.surface_rest, hand.surface_bone, 0.4 * SPACING_M,
                         hand.surface_normal_rest)
        self.skin = hand

    def posed(self, angles: np.ndarray, normals: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        points, n = self.skin.surface_points(angles, normals=normals)
        return points, n


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def test_contact_value_binary_and_soft():
    d = np.array([0.0, 0.002, 0.0039, 0.004, 0.01, np.inf])
    assert contact_value(d).tolist() == [1, 1, 1, 0, 0, 0]
    assert np.allclose(contact_value(d, soft=True), [1, 0.5, 0.025, 0, 0, 0])


def test_true_geometry_reproduces_the_exact_contact(scene):
    """Contact of the true skin against points on the true object surface agrees with the
    simulator's contact at the same distance computed from the exact SDF: the contact code is right."""
    maps = hand_object_contacts(scene["truth_hand"], scene["angles"], scene["object"])
    grasp = scene["grasp"]
    frame, vertex = grasp.hand.contact(scene["angles"], grasp.object, scene["pose"], TAU_M)
    exact = np.zeros((len(scene["angles"]), grasp.hand.n_points), bool)
    exact[frame, vertex] = True
    assert maps.instant.shape == exact.shape
    assert exact.any(axis=0).sum() > 200
    # object points ~1 mm apart under-estimate the distance by at most that: the boundary of a
    # 4 mm band moves by well under a point spacing
    agreement = iou(maps.accumulated > 0.5, exact.any(axis=0))
    assert agreement > 0.9, agreement
    hold = np.argmax(exact.sum(axis=1))
    assert iou(maps.instant[hold] > 0.5, exact[hold]) > 0.85
    # the paint is what touched: a part of the 4 mm band
    paint = grasp.motion.contact_accumulated()
    assert 100 < paint.sum() and exact.any(axis=0)[paint].mean() > 0.95
    # the object side: points touched are near the hand's contact, and there are some
    assert 0 < maps.object_accumulated.sum() < len(scene["object"])


def test_frames_without_a_hand_have_no_contact(scene):
    angles = scene["angles"].copy()
    angles[:] = np.nan
    maps = hand_object_contacts(scene["truth_hand"], angles[:5], scene["object"])
    assert not maps.instant.any() and not maps.accumulated.any()


def test_true_contact_rendered_on_the_canonical_pose_matches_the_paint_labels(scene):
    """Rendering the true contact on the true canonical pose into the views that show paint
    reproduces the renderer's paint labels (both in raw, distorted pixels)."""
    cube = scene["canonical"]
    tick = float(cube.tick_ns(3))
    labels = np.stack([cube.render(c, tick, labels=True).labels for c in range(len(cube.cameras))])
    paint = labels == 3
    views = pick_views(paint, 10)
    assert len(views) >= 5
    canonical = cube.motion.hand_angles(np.array([cube.seconds(tick)]))[0]
    truth = cube.motion.contact_accumulated().astype(np.float32)
    scores, pred = score_contacts(scene["truth_hand"], canonical, truth, cube.cameras, paint, views)
    # The only differences are at the paint's edges: the regions are 20-80 px at 320x180 (a pixel
    # is 2-3 mm), so half a pixel of boundary costs a quarter of the IoU (measured 0.68; template 0.58).
    assert scores.mean_iou > 0.65 and scores.pooled_iou > 0.65, scores.to_json()
    template = capsule_template(cube.hand.skeleton.bone_lengths)
    maps = hand_object_contacts(template, scene["angles"], scene["object"])
    baseline, _ = score_contacts(template, canonical, maps.accumulated, cube.cameras, paint, views)
    assert baseline.mean_iou < scores.mean_iou


def test_render_values_reads_back_a_constant(scene):
    V = torch.eye(4)[None]
    V[0, 2, 3] = 0.5
    K = torch.tensor([[[200.0, 0, 63.5], [0, 200.0, 63.5], [0, 0, 1]]])
    hand = scene["truth_hand"]
    angles = np.zeros(26)
    premultiplied, alpha = render_values(hand, angles, np.full(len(hand), 0.25), V, K, 128, 128)
    value = surface_value(premultiplied, alpha)
    covered = alpha > 0.5
    assert covered.sum() > 500 and np.allclose(value[covered], 0.25, atol=1e-4)


def test_mask_scores_against_hand_computed_values():
    pred = np.zeros((2, 4, 4), bool)
    truth = np.zeros((2, 4, 4), bool)
    pred[0, :2] = True          # 8 px
    truth[0, 1:3] = True        # 8 px, 4 shared
    scores = mask_scores(pred, truth, ("a", "b"))
    assert np.allclose(scores.iou, [4 / 12, 1.0]) and np.allclose(scores.f1, [0.5, 1.0])
    assert np.isclose(scores.pooled_iou, 4 / 12) and np.isclose(scores.pooled_f1, 0.5)
    with pytest.raises(EvaluateError, match="shape"):
        mask_scores(pred[:1], truth, ("a",))


def test_view_choice_and_camera_spread(scene):
    paint = np.zeros((5, 8, 8), bool)
    paint[1, :5] = True
    paint[3, :3] = True
    assert pick_views(paint, 10, min_px=10).tolist() == [1, 3]
    with pytest.raises(EvaluateError, match="paint"):
        pick_views(np.zeros((3, 4, 4), bool))
    rig = scene["canonical"].cameras
    four = spread_cameras(rig, 4)
    assert len(four) == 4 and len(set(four.tolist())) == 4
    centres = rig.centers[four]
    spacing = np.linalg.norm(centres[:, None] - centres[None], axis=-1)[np.triu_indices(4, 1)]
    assert spacing.min() > 0.5  # on a ~1 m cube, four spread cameras are not neighbours
    assert spread_cameras(rig, 100).tolist() == list(range(len(rig)))


def test_canonical_pose_is_the_median_of_fitted_frames():
    angles = np.zeros((5, 26))
    angles[:, 0] = [0.1, 0.2, 0.3, np.nan, 5.0]
    assert np.isclose(canonical_pose(angles)[0], 0.25)
    with pytest.raises(EvaluateError):
        canonical_pose(np.full((3, 26), np.nan))


@pytest.mark.parametrize("on_disk", [False, True])
def test_contact_store_puts_ranges_together_in_any_order(tmp_path, on_disk):
    """The ranges of a take's maps, finishing in any order, go into a ContactStore (arrays, or a
    file so that a long take's maps need not fit in memory); the maps written into DATASET.h5 are
    those of the whole take in one piece, and the file is gone after."""
    import h5py

    from manus_capture.contact_tasks import ContactStore
    from manus_capture.contacts import accumulate, write_contacts

    rng = np.random.default_rng(0)
    hand, obj = rng.random((100, 50)).astype(np.float32), (rng.random((100, 30)) < 0.1).astype(np.float32)
    store = ContactStore(100, 50, 30, tmp_path / "store.h5" if on_disk else None)
    for start in (64, 0, 96, 32):
        store.put(start, accumulate(hand[start:start + 32], obj[start:start + 32], TAU_M, True))
    write_contacts(tmp_path / "D.h5", "S/t", store.maps(TAU_M, True), {})
    store.close()
    whole = accumulate(hand, obj, TAU_M, True)
    with h5py.File(tmp_path / "D.h5") as f:
        np.testing.assert_array_equal(f["S/t/contacts/instant"][()], whole.instant.astype(np.float16))
        np.testing.assert_array_equal(f["S/t/contacts/object_instant"][()], whole.object_instant.astype(np.float16))
        np.testing.assert_array_equal(f["S/t/contacts/accumulated"][()], whole.accumulated)
        np.testing.assert_array_equal(f["S/t/contacts/object_accumulated"][()], whole.object_accumulated)
    np.testing.assert_allclose(store.totals, hand.sum(axis=1), rtol=1e-6)
    assert not (tmp_path / "store.h5").exists()


def test_capsule_distances_each_point_against_each_capsule():
    """The template's geometry (and the learned hand's start surface): signed, negative inside."""
    a = np.array([[0, 0, 0], [1, 0, 0.0]])
    b = np.array([[0, 0, 1], [1, 0, 1.0]])
    d = capsule_distances(np.array([[0.5, 0, 0.5], [-1, 0, 2], [1.2, 0, 0.5]]), a, b, np.array([0.1, 0.3]))
    np.testing.assert_allclose(d, [[0.4, 0.2], [np.sqrt(2) - 0.1, np.sqrt(5) - 0.3], [1.1, -0.1]])
