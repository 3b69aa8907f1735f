"""surface_errors: a model's rest surface against the true skin, in any frame of its own."""

from __future__ import annotations

import numpy as np

from manus_capture.surface_score import surface_errors
from manus_core.ground_truth import TruthSkin
from manus_core.rotations import rotvec_to_matrix


def test_points_off_the_skin_by_known_amounts_in_another_frame():
    rng = np.random.default_rng(0)
    normals = rng.normal(size=(4000, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    points = 0.05 * normals                     # a sphere of 5 cm, normals outward
    bone = np.where(points[:, 1] > 0, 5, 4)     # upper half on a phalanx, lower on a metacarpal
    skin = TruthSkin(points, normals, bone, np.zeros((0, 3), np.int64), np.zeros((4000, 20)))
    true_joints = rng.normal(scale=0.04, size=(21, 3))
    # the model: fingers 1 mm outside, palm 2 mm inside, in a frame turned and moved
    offset = np.where(bone == 5, 1e-3, -2e-3)[:, None] * normals
    R, t = rotvec_to_matrix(np.array([0.3, -1.1, 0.5])), np.array([0.2, -0.1, 0.4])
    model = (points + offset - t) @ R          # R^T (x - t): the truth is R model + t
    joints = (true_joints - t) @ R
    errors = surface_errors(model, joints, skin, true_joints)
    assert abs(errors["fingers_mm"] - 1.0) < 0.05 and abs(errors["fingers_signed_mm"] - 1.0) < 0.05
    assert abs(errors["palm_mm"] - 2.0) < 0.05 and abs(errors["palm_signed_mm"] + 2.0) < 0.05
    assert errors["joints_mm"] < 1e-6
