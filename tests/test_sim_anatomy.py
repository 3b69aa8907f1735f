"""The anatomical simulated hand against the capsule class, its ground truth, and subject files."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from click.testing import CliRunner

from manus_capture.cli import cli
from manus_capture.template import capsule_template
from manus_core.errors import SessionError
from manus_core.ground_truth import GroundTruth
from rig.layouts import make_rig
from rig.sim.cube import SimulatedCube
from rig.sim.hand import SUBJECTS, capsule_fit, load_subject, make_hand, subject_toml
from rig.sim.subject import with_sim_subject


@pytest.mark.parametrize("name", SUBJECTS)
def test_the_skin_is_out_of_the_capsule_class(name):
    """The best capsule per phalanx leaves at least 1.2 mm RMS and 2 mm at the 90th percentile on
    every subject (docs/simulation.md has the table), where the capsule hand it replaced left
    0.5-0.8 mm and 0.5-1.0 mm: a template of capsules cannot describe it."""
    hand = make_hand(name)
    residual = np.abs(capsule_fit(hand.surface_rest, hand.surface_bone, hand.rest.joints))
    assert np.sqrt(np.mean(residual ** 2)) >= 1.2e-3
    assert np.percentile(residual, 90) >= 2.0e-3


def test_the_capsule_template_is_still_capsules():
    """The baseline keeps its class, and the measure tells it from the skin: measured 0.59 mm, all
    of it at the fingertips, where a distal capsule stops a radius short of the tip keypoint that
    the fitted segment runs to; the skin's floor is twice that."""
    template = capsule_template(SUBJECTS["s01"].bone_lengths)
    joints = template.skeleton.rest_joints()
    finger = template.bone % 4 != 0
    residual = capsule_fit(template.points_rest[finger], template.bone[finger], joints)
    assert np.sqrt(np.mean(residual ** 2)) < 0.7e-3


def test_subjects_differ_in_flesh_and_colour():
    """Finger girth, pad fullness, palm width and depth and skin colour all vary across subjects."""
    shapes = list(SUBJECTS.values())
    for key in ("finger_thickness", "pad_fullness", "palm_width", "palm_thickness"):
        values = [getattr(s, key) for s in shapes]
        assert max(values) - min(values) >= 0.15, key
    brightness = [np.mean(s.skin_rgb) for s in shapes]
    assert max(brightness) - min(brightness) > 0.2


def test_ground_truth_holds_the_rest_skin(tmp_path):
    cfg = make_rig("cube53", cameras=6, resolution=(160, 90))
    cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, subject="s02"))
    cube = SimulatedCube(cfg, "hand", 0.2)
    cube.write_ground_truth(tmp_path / "ground_truth.h5", label_frames=[])
    gt = GroundTruth(tmp_path / "ground_truth.h5")
    hand = make_hand("s02")
    skin = gt.skin
    np.testing.assert_array_equal(skin.points, hand.surface_rest)
    np.testing.assert_array_equal(skin.bone, hand.surface_bone)
    assert skin.bone.dtype.kind == "i" and set(np.unique(skin.bone)) <= set(range(20))
    np.testing.assert_allclose(np.linalg.norm(skin.normals, axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(gt.hand.rest_joints, hand.skeleton.rest_joints())
    assert skin.faces.max() < len(skin.points)
    # the skin of a frame from the file alone: its weights blend the bones' motions
    angles = cube.motion.hand_angles(np.array([0.1]))[0]
    rot, trans = hand.skeleton.bone_transforms(angles)
    rebuilt = np.einsum("nb,bij,nj->ni", skin.weights, rot, skin.points) + skin.weights @ trans
    np.testing.assert_allclose(rebuilt, hand.surface_points(angles)[0], atol=1e-6)
    # the subject's parameters read back as the same shape
    (tmp_path / "s02.toml").write_text(skin.subject_toml)
    again = load_subject(tmp_path / "s02.toml")
    np.testing.assert_allclose(again.bone_lengths, hand.shape.bone_lengths)
    assert dataclasses.replace(again, bone_lengths=None) == dataclasses.replace(hand.shape, bone_lengths=None)


def _demo(tmp_path, subject: str):
    return CliRunner().invoke(cli, ["demo", "-o", str(tmp_path / "out"), "--subject", subject])


def test_an_unknown_subject_lists_the_known_ones(tmp_path):
    result = _demo(tmp_path, "s99")
    assert result.exit_code == 2
    assert "unknown subject 's99'" in result.output and "s01, s02, s03" in result.output
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("text, key", [
    ("finger_thickness = -0.2", "finger_thickness"),
    ("pad_fullness = 3.0", "pad_fullness"),
    ("palm_width = 2.5", "palm_width"),
    ("skin_rgb = [1.2, 0.5, 0.4]", "skin_rgb"),
    ("thumb_length = 2", "thumb_length"),
])
def test_an_impossible_subject_file_names_the_key(tmp_path, text, key):
    path = tmp_path / "odd.toml"
    path.write_text(f'name = "odd"\n{text}\n')
    result = _demo(tmp_path, str(path))
    assert result.exit_code == 2
    assert str(path) in result.output and key in result.output
    assert not (tmp_path / "out").exists()


def test_a_subject_file_makes_a_hand(tmp_path):
    path = tmp_path / "wide.toml"
    path.write_text(subject_toml(dataclasses.replace(SUBJECTS["s01"], name="wide", palm_width=1.3)))
    wide, average = make_hand(str(path)), make_hand("s01")

    def palm_span(hand) -> float:
        """The palm's width across its middle, the thumb's flesh left out."""
        p = hand.surface_rest
        mid = (np.abs(p[:, 1] - 0.05) < 0.005) & (hand.surface_bone % 4 == 0)
        return float(np.ptp(p[mid, 0]))

    # measured 9.1 cm against 7.1 cm: the sides move out by 30 % of their distance from the middle
    assert wide.subject == "wide" and palm_span(wide) > palm_span(average) + 0.008


def test_an_unknown_object_lists_the_known_ones(tmp_path):
    result = CliRunner().invoke(cli, ["demo", "-o", str(tmp_path / "out"), "--object", "cup"])
    assert result.exit_code == 2 and "'cup'" in result.output
    assert all(name in result.output for name in ("mug", "box", "sphere"))
    # record and protocol take it through the rig: one line naming the rig file and the choices
    with pytest.raises(SessionError, match=r"no object 'cup' \(known: box, mug, sphere\)"):
        with_sim_subject(make_rig("cube53", cameras=6), obj="cup")
    with pytest.raises(SessionError, match=r"no subject 's9' \(known: s01, s02, s03"):
        with_sim_subject(make_rig("cube53", cameras=6), subject="s9")
