"""`manus-capture segment` end to end: recorded simulated takes -> DATASET.h5 masks scored against
the per-pixel truth of ground_truth.h5, overlays written, bad input reported."""

from __future__ import annotations

import dataclasses
import json
import shutil

import cv2
import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from dataset_tools.sync import frame_groups
from manus_capture.cli import cli
from manus_core.cameras import CameraRig
from manus_core.dataset import take_key
from manus_core.ground_truth import GroundTruth
from manus_core.provenance import provenance_attrs
from rig.layouts import make_rig
from rig.record import RecordOptions, record_take
from rig.sim.cube import true_cameras

W, H = 320, 180


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def _record(root, take, kind, seconds, ticks):
    """empty (the background), object and `take` of one simulated rig, and its true calibration."""
    # triggered cameras expose on the tick, so the labels of a tick are what every view saw
    rig = make_rig("cube53", cameras=5, resolution=(W, H), sync="hardware-trigger", seed=3)
    rig = dataclasses.replace(rig, sim=dataclasses.replace(rig.sim, paint=True, object="mug"))
    for name, kind_, secs, labelled in [("empty", "calibration", 0.03, []), ("object", "object", 0.02, [0]),
                                        (take, kind, seconds, ticks)]:
        assert record_take(rig, root / "S", name, kind_, secs, RecordOptions(label_frames=labelled)).status == "complete"
    true_cameras(rig).save(root / "cameras.json")
    return root


# one small session per test module fixture, so that pytest-xdist workers do not record each other's
@pytest.fixture(scope="module")
def grasp_session(tmp_path_factory):
    return _record(tmp_path_factory.mktemp("grasp"), "grasp", "grasp", 0.03, [0, 3])


@pytest.fixture(scope="module")
def canon_session(tmp_path_factory):
    return _record(tmp_path_factory.mktemp("canon"), "canon", "canonical", 0.02, [0, 1, 2, 3])


def _segment(session, take, *extra):
    out = session / f"{take}{len(list(session.glob('*.h5')))}.h5"
    args = ["segment", str(session / "S" / take), "--calib", str(session / "cameras.json"),
            "--background", str(session / "S" / "empty"), "-o", str(out), *extra]
    return CliRunner().invoke(cli, args), out


def _truth(session, take, frame_ns):
    gt = GroundTruth.of_take(session / "S" / take)
    tick, frames, labels = gt.tick_at(frame_ns), gt.label_frames.tolist(), gt.labels()
    keep = [t for t, k in enumerate(tick) if k in frames]
    return keep, labels[:, [frames.index(tick[t]) for t in keep]].transpose(1, 0, 2, 3)


def _read(out, session, take, *names):
    """Arrays `names` of the take's group in DATASET.h5 `out`."""
    with h5py.File(out) as f:
        group = f[take_key(session / "S" / take)]
        return [group[name][()] for name in names]


def test_segment_grasp_take_into_dataset(grasp_session):
    session = grasp_session
    result, out = _segment(session, "grasp", "--object-take", str(session / "S" / "object"), "--every", "3",
                           "--overlays", str(session / "overlays"))
    assert result.exit_code == 0, result.output
    with h5py.File(out) as f:
        group = f[take_key(session / "S" / "grasp")]
        hand, obj = group["masks/hand"][()], group["masks/object"][()]
        frame_ns = group["masks/frame_ns"][()]
        assert group["masks/hand"].compression == "gzip"
    # the masks were written to a file beside the dataset as they came, then copied in and removed
    assert not list(out.parent.glob(".*.masks.h5"))
    assert f"segment: {len(frame_ns)} groups x 5 cameras" in result.output
    keep, truth = _truth(session, "grasp", frame_ns)
    assert len(keep) == 2   # the groups of ticks 0 and 3, found again through masks/frame_ns
    hand_iou = iou(hand[keep], (truth == 1) | (truth == 3))
    obj_iou = iou(obj[keep], truth == 2)
    # at 320x180 finger edges are a large share of the masks: measured 0.915 / 0.964; the issue's
    # 0.95 is tested at 640x360 in test_segmentation.py
    assert hand_iou >= 0.9 and obj_iou >= 0.93, (hand_iou, obj_iou)
    # the masks are there, made from the same inputs: kept, the file untouched
    before = out.read_bytes()
    again = CliRunner().invoke(cli, ["segment", str(session / "S" / "grasp"), "--calib", str(session / "cameras.json"),
                                     "--background", str(session / "S" / "empty"), "--object-take",
                                     str(session / "S" / "object"), "--every", "3", "-o", str(out)])
    assert again.exit_code == 0 and f"kept (same inputs): the masks of S/grasp in {out}" in again.output, again.output
    assert out.read_bytes() == before
    # the capture day's step 6 before annotate: stats failed on the whole file (`take
    # S/grasp/masks: missing frame_index`); it lists the take and what it holds
    stats = CliRunner().invoke(cli, ["stats", str(out)])
    assert stats.exit_code == 0 and "1 takes, 0 frames" in stats.output and "not annotated: S/grasp" in stats.output
    overlays = sorted((session / "overlays").glob("*.png"))
    assert len(overlays) == 5 and all(cv2.imread(str(p)).shape == (H, W, 3) for p in overlays)


def test_segment_redoes_the_masks_of_a_re_recorded_take(grasp_session, tmp_path):
    """The masks record what made them (the take's recording, the calibration, the settings): a
    second run keeps them only when all of it is the same, and otherwise redoes them, saying why."""
    session = grasp_session
    take = tmp_path / "S" / "grasp"   # the same key, S/grasp, in a folder this test may change
    shutil.copytree(session / "S" / "grasp", take)
    out = tmp_path / "D.h5"
    args = ["segment", str(take), "--calib", str(session / "cameras.json"), "--background",
            str(session / "S" / "empty"), "--every", "5", "-o", str(out)]
    assert CliRunner().invoke(cli, args).exit_code == 0
    # recorded again: here one camera's last frame is gone
    cam = CameraRig.load(session / "cameras.json").ids[0]
    rows = (take / "frames.csv").read_text().splitlines()
    last = max(i for i, row in enumerate(rows) if row.startswith(cam + ","))
    (take / "frames.csv").write_text("\n".join(rows[:last] + rows[last + 1:]) + "\n")
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    frames = sum(row.startswith(cam + ",") for row in rows)
    assert f"redone the masks of S/grasp: take re-recorded: frames of {cam} {frames} -> {frames - 1}" in result.output
    result = CliRunner().invoke(cli, [*args[:-2], "--every", "4", "-o", str(out)])
    assert result.exit_code == 0 and "redone the masks of S/grasp: every 5 -> 4" in result.output, result.output
    with h5py.File(out) as f:
        inputs = json.loads(f["S/grasp"].attrs["provenance_segment"])
    assert inputs["take"]["frames"][cam] == frames - 1 and inputs["every"] == 4


def test_segment_object_take_is_all_object(grasp_session):
    """The object take has no hand in it: its whole foreground is object, including the shading
    that a colour split would take for skin (it used to cut 1-2 px off the object's edges, and the
    object model trained on those masks shrank by as much)."""
    session = grasp_session
    result, out = _segment(session, "object", "--object-take", str(session / "S" / "object"))
    assert result.exit_code == 0, result.output
    hand, obj, frame_ns = _read(out, session, "object", "masks/hand", "masks/object", "masks/frame_ns")
    keep, truth = _truth(session, "object", frame_ns)
    assert keep and not hand.any()
    assert iou(obj[keep], truth == 2) >= 0.95, iou(obj[keep], truth == 2)
    # views without a mask are never written: no chunk stored, no time spent compressing nothing
    with h5py.File(out) as f:
        group = f[take_key(session / "S" / "object")]
        assert group["masks/hand"].id.get_num_chunks() == 0
        assert group["masks/object"].id.get_num_chunks() == int(obj.any(axis=(2, 3)).sum()) > 0


def test_segment_canonical_paint(canon_session):
    session = canon_session
    result, out = _segment(session, "canon", "--object-take", str(session / "S" / "object"))
    assert result.exit_code == 0, result.output
    paint, hand, frame_ns = _read(out, session, "canon", "paint/masks", "masks/hand", "masks/frame_ns")
    middle = len(frame_ns) // 2   # the group the paint is segmented in
    _, truth = _truth(session, "canon", frame_ns[middle:middle + 1])
    assert paint.shape == truth[0].shape
    hand_iou = iou(hand[middle], (truth[0] == 1) | (truth[0] == 3))
    paint_iou = iou(paint, truth[0] == 3)
    # 320x180, spots of 50-220 px: measured hand 0.96, paint 0.84 pooled over the views; see
    # test_segmentation.py for the targets at 1280x720
    assert hand_iou >= 0.92 and paint_iou >= 0.75, (hand_iou, paint_iou)


def test_segment_bad_input(canon_session, tmp_path):
    session = canon_session
    # no background take: one line, exit code 2
    result = CliRunner().invoke(cli, ["segment", str(session / "S" / "canon"), "--calib", str(session / "cameras.json"),
                                      "--background", str(tmp_path / "nothing"), "-o", str(tmp_path / "d.h5")])
    assert result.exit_code == 2 and "nothing" in result.output, result.output
    # a camera of the take missing from the calibration (calibrate --allow-partial): the others are
    # segmented and the warning names it
    rig = CameraRig.load(session / "cameras.json")
    rig.subset(rig.ids[:-1]).save(tmp_path / "four.json")
    args = ["segment", str(session / "S" / "canon"), "--calib", str(tmp_path / "four.json"),
            "--background", str(session / "S" / "empty"), "--every", "4", "-o", str(tmp_path / "d.h5")]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    assert f"warning: cameras {rig.ids[-1]} are not in the calibration: left out (masks of 4 of 5" in result.output
    with h5py.File(tmp_path / "d.h5") as f:
        group = f[take_key(session / "S" / "canon")]
        assert list(group.attrs["mask_cameras"]) == list(rig.ids[:-1]) and group["masks/hand"].shape[1] == 4
    # --cameras: a camera the calibration lacks, one not in the take, or fewer than 2: one line, exit code 2
    for cameras, problem in [(rig.ids[-1], f"cameras {rig.ids[-1]} are not in the calibration"),
                             ("nope", "no camera nope in this take"), (rig.ids[0], "masks need at least 2")]:
        result = CliRunner().invoke(cli, [*args, "--cameras", cameras, "--force"])
        assert result.exit_code == 2 and problem in result.output and "Traceback" not in result.output, result.output
    # a camera missing from the background take: a warning, its masks empty, the others still segmented
    empty = tmp_path / "empty"
    shutil.copytree(session / "S" / "empty", empty)
    rows = (empty / "frames.csv").read_text().splitlines()
    (empty / "frames.csv").write_text("\n".join(r for r in rows if not r.startswith(rig.ids[0] + ",")) + "\n")
    out = tmp_path / "partial.h5"
    result = CliRunner().invoke(cli, ["segment", str(session / "S" / "canon"), "--calib", str(session / "cameras.json"),
                                      "--background", str(empty), "--object-take", str(session / "S" / "object"),
                                      "--every", "4", "-o", str(out)])
    assert result.exit_code == 0 and f"warning: camera {rig.ids[0]}: no frames in background take" in result.output
    assert "(1 warnings" in result.output
    hand, = _read(out, session, "canon", "masks/hand")
    assert not hand[:, 0].any() and hand[:, 1:].any()
    # a canonical take without a paint colour: a warning, never silence
    result, _ = _segment(session, "canon", "--every", "4")
    assert result.exit_code == 0 and "warning: canonical take without" in result.output
    # a paint colour that is not on the hand
    result, _ = _segment(session, "canon", "--swatch", "255,40,40", "--every", "4")
    assert result.exit_code == 0 and "no paint colour found" in result.output, result.output


def _groups(session, take):
    groups = frame_groups(session / "S" / take)
    return groups.frame_ns, groups.frame_index


def test_segment_masks_made_by_another_tool(canon_session, tmp_path):
    session = canon_session
    frame_ns, frame_index = _groups(session, "canon")
    keep, truth = _truth(session, "canon", frame_ns)
    assert keep == list(range(len(frame_ns)))
    cams = CameraRig.load(session / "cameras.json").ids
    # a camera without a frame in a group (a drop) has no mask there
    hand_truth = ((truth == 1) | (truth == 3)) & (frame_index >= 0)[..., None, None]
    for t, c in zip(*np.nonzero(frame_index >= 0)):
        (tmp_path / "masks" / "hand" / cams[c]).mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(tmp_path / "masks" / "hand" / cams[c] / f"{frame_index[t, c]:06d}.png"),
                    hand_truth[t, c].astype(np.uint8) * 255)
    result, out = _segment(session, "canon", "--masks", str(tmp_path / "masks"),
                           "--object-take", str(session / "S" / "object"))
    assert result.exit_code == 0, result.output
    hand, obj, paint = _read(out, session, "canon", "masks/hand", "masks/object", "paint/masks")
    assert np.array_equal(hand, hand_truth) and not obj.any()
    middle = len(frame_ns) // 2
    # inside the true hand masks: measured 0.83 (0.84 inside segmented ones: test_segment_canonical_paint)
    assert iou(paint, truth[middle] == 3) >= 0.75, iou(paint, truth[middle] == 3)
    # the masks stand in for the background: a swatch gives the paint colour
    args = ["segment", str(session / "S" / "canon"), "--calib", str(session / "cameras.json"), "--masks",
            str(tmp_path / "masks"), "--swatch", "51,199,31", "-o", str(tmp_path / "swatch.h5")]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0 and "paint in" in result.output, result.output
    # a mask missing: one line naming the file, exit code 2
    missing = tmp_path / "masks" / "hand" / cams[1] / f"{frame_index[0, 1]:06d}.png"
    missing.unlink()
    result = CliRunner().invoke(cli, [*args[:-1], str(tmp_path / "again.h5")])
    assert result.exit_code == 2 and f"{missing}: missing or not an image" in result.output, result.output
    # masks without a background: the object take's paint colour cannot be found
    result = CliRunner().invoke(cli, args[:6] + ["--object-take", str(session / "S" / "object"), "-o",
                                                 str(tmp_path / "object.h5")])
    assert result.exit_code == 2 and "--swatch for the paint colour" in result.output, result.output
    # neither a background nor masks
    result = CliRunner().invoke(cli, args[:4] + ["--swatch", "51,199,31", "-o", str(tmp_path / "none.h5")])
    assert result.exit_code == 2 and "no background take" in result.output, result.output


def test_segment_paint_on_the_hand_surface(canon_session, tmp_path):
    """With annotate's poses in DATASET.h5, the paint masks are voted onto the capsule template's
    surface points; the votes agree with the simulator's true paint on the hand."""
    from scipy.spatial import cKDTree

    from manus_core.dataset import add_arrays

    session = canon_session
    frame_ns, _ = _groups(session, "canon")
    gt = GroundTruth.of_take(session / "S" / "canon")
    tick = gt.tick_at(frame_ns)
    angles, bones = gt.hand.joint_angles[tick], gt.hand.bone_lengths
    true_points, true_paint = gt.contact.points_rest, gt.contact.accumulated > 0.5
    out = tmp_path / "D.h5"
    # what annotate stores, with the true poses
    add_arrays(out, take_key(session / "S" / "canon"), {"frame_ns": frame_ns, "joint_angles": angles,
                                                         "bone_lengths": bones})
    args = ["segment", str(session / "S" / "canon"), "--calib", str(session / "cameras.json"), "--background",
            str(session / "S" / "empty"), "--object-take", str(session / "S" / "object"), "-o", str(out)]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0 and "seen surface points" in result.output, result.output
    value, voters, points = _read(out, session, "canon", "paint/contact", "paint/voters", "paint/points_rest")
    seen = voters > 0
    assert seen.mean() > 0.5 and np.isnan(value[~seen]).all()
    # the template's surface is within a few millimetres of the simulated hand's: each of its
    # points takes the truth of the nearest simulated surface point
    dist, nearest = cKDTree(true_points).query(points)
    scored = seen & (dist < 0.004)
    voted, true = value[scored] > 0.5, true_paint[nearest[scored]]
    score = (voted & true).sum() / max((voted | true).sum(), 1)
    # 5 cameras at 320x180: measured IoU 0.64 (0.80 on the capsule hand, whose paint was every point
    # within 4 mm of the object: the skin that touched is a smaller region on a surface the template
    # now misses by millimetres, so more of it is edge)
    assert score >= 0.55, score
    # poses annotated from an earlier recording of the take: the paint is not voted with them, and
    # the note says why
    add_arrays(out, take_key(session / "S" / "canon"), {},
               provenance_attrs("annotate", {"take": {"frames": {}, "frames_csv_sha256": ""}}))
    result = CliRunner().invoke(cli, [*args, "--every", "4"])
    assert result.exit_code == 0 and "poses of S/canon are of another recording (take re-recorded" in result.output
    assert "seen surface points" not in result.output


def test_reconstruct_object_on_a_partial_calibration(grasp_session, tmp_path):
    """After calibrate --allow-partial, reconstruct uses the calibrated cameras and names the others."""
    session = grasp_session
    rig = CameraRig.load(session / "cameras.json")
    rig.subset(rig.ids[1:]).save(tmp_path / "four.json")
    args = ["reconstruct", "object", "--take", str(session / "S" / "object"), "--cameras", str(tmp_path / "four.json"),
            "--masks", "truth", "--iterations", "2", "--points", "200", "-o", str(tmp_path / "object.safetensors")]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    assert f"note: cameras {rig.ids[0]} of {session / 'S' / 'object'} are not in the calibration: left out" \
        in result.output and "from 4 views" in result.output
    result = CliRunner().invoke(cli, [*args, "--only-cameras", rig.ids[1], "--force"])
    assert result.exit_code == 2 and "training needs at least 2" in result.output, result.output
