"""The demo end to end at a small size: every stage runs on recorded simulated takes and is
scored against the simulator's truth; the report and summary.json carry the figures."""

from __future__ import annotations

import json
import shutil

import h5py
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from dataset_tools.calibration.formats import load_cameras
from manus_capture import api
from manus_capture.cli import cli
from manus_capture.demo import Demo, DemoConfig
from manus_capture.pose_score import truth_at_groups
from manus_capture.splat.checkpoint import load_checkpoint, save_checkpoint
from manus_capture.splat.hand import HandGaussians
from manus_capture.splat.takes import hand_frames_from_dataset, spread_frames
from manus_core.ground_truth import GroundTruth
from manus_core.rig_config import rig_to_toml
from manus_core.skeleton import HandSkeleton
from rig.sim.subject import with_sim_subject

# the Gaussian hand's least lead over the template that both seeds must keep
MARGIN = 1.10
# The stages after annotate are held to figures measured with the simulated detector (the true joints
# with 2 px of noise and 10 % outliers), whose keypoints are the same on every machine; what the
# demo's default, the ONNX detector on the frames, gives is test_default_keypoints_are_the_onnx_detectors.
ARGS = ["--cameras", "12", "--resolution", "320x180", "--fps", "20", "--views", "3,6,all", "--iterations", "300",
        "--refine-iterations", "5", "--simulated-keypoints"]


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "run"
    result = CliRunner().invoke(cli, ["demo", "-o", str(out), *ARGS])
    assert result.exit_code == 0, result.output
    return out, json.loads((out / "summary.json").read_text()), result.output


def stage(summary: dict, name: str) -> dict:
    return next(s for s in summary["stages"] if s["name"] == name)["metrics"]


def test_every_stage_ran_and_the_report_shows_it(demo):
    out, summary, output = demo
    names = [s["name"] for s in summary["stages"]]
    assert names == ["record", "sync", "calibrate", "annotate", "segment", "reconstruct", "refine", "contacts",
                     "evaluate"]
    for key in ("contact_iou", "contact_f1", "baseline_iou", "baseline_f1"):
        assert 0.0 <= summary[key] <= 1.0
    assert set(summary["views"]) == {"3", "6", "12"}
    html = (out / "report.html").read_text()
    assert "finger_angle_rms_deg_refined" in html
    images = sorted(p.name for p in (out / "images").glob("*.png"))
    assert any(n.startswith("keypoints_") for n in images) and any(n.startswith("contact_") for n in images)
    assert {"ablation.png", "sync_timeline.png"} <= set(images)
    for name in images:
        assert f"images/{name}" in html
    assert "demo: contact IoU" in output and (out / "DATASET.h5").stat().st_size > 0


def test_stages_agree_with_the_simulators_truth(demo):
    _, summary, _ = demo
    sync = stage(summary, "sync")
    assert sync["drops_found"] == sync["drops_true"]
    calib = stage(summary, "calibrate")
    # intrinsics and poses from the tags alone, 12 cameras at 320x180 (measured: focal length 0.16 %,
    # principal point 0.62 px, centres 2.3 mm, rotations 0.15 deg at worst; the 53-camera test at
    # 640x360 holds 0.3 %, 1 px, 2 mm, 0.1 deg)
    assert calib["fx_err_pct_max"] < 0.5 and calib["pp_err_px_max"] < 2.0, calib
    assert calib["centre_err_mm_max"] < 5 and calib["rotation_err_deg_max"] < 0.3, calib
    ann = stage(summary, "annotate")
    # 2 px detector noise at 320x180 is ~5 mm per view at 1 m; 12 views and the skeleton bring it down
    assert ann["fitted_mpjpe_mm"] < 8 and ann["bone_length_err_mm"] < 4, ann
    seg = stage(summary, "segment")
    assert seg["object_iou"] > 0.9 and seg["hand_iou"] > 0.9 and seg["paint_iou"] > 0.5, seg
    rec = stage(summary, "reconstruct")
    assert rec["hand_psnr_heldout_poses_db"] > 24 and rec["object_psnr_heldout_views_db"] > 28, rec
    # the learned fingers lie nearer the true skin than the template's (measured 1.28 against 2.03 mm)
    assert rec["hand_surface_fingers_mm"] < 0.9 * rec["template_surface_fingers_mm"], rec
    refine = stage(summary, "refine")
    # keypoints, smoothness, silhouettes and colour through MANUS-Hand (docs/refine.md; measured
    # here 8.36 -> 4.65 deg and 3.06 -> 2.18 mm, seed 1 8.74 -> 4.91 deg; the 24-camera demo 5.25 ->
    # 3.23 deg, 2.16 -> 1.26 mm)
    assert summary["finger_angle_rms_deg_refined"] < 0.85 * summary["finger_angle_rms_deg"], summary
    assert refine["fitted_mpjpe_mm_refined"] < ann["fitted_mpjpe_mm"], (refine, ann)
    for name in ("hand_psnr_mask_db", "object_psnr_mask_db", "finger_angle_rms_deg", "finger_angle_rms_deg_refined"):
        assert np.isfinite(summary[name]), name
    # LPIPS of the held-out views with the installed network (make test installs it), over the whole
    # view as PSNR and SSIM: most of a view is the empty cube on both sides (measured here: hand
    # 0.0028, object 0.0032; on the 24-camera demo 0.0035 and 0.0016)
    for name in ("hand_lpips", "object_lpips"):
        assert 0 < summary[name] < 0.05, (name, summary[name])
    # on the hand's own pixels over black: 11.4 dB when the hand started without a wrist (a third of
    # its mask pixels uncovered), 15.4 dB with it; over the empty cube, as the cameras see the hand,
    # 19.0 dB (the wall's share of the silhouette's pixels no longer counts against the model); with the
    # view-dependent colour learnt and larger centre steps 18.6 and 21.8 dB
    assert rec["hand_psnr_mask_black_db"] > 13.5, rec
    assert summary["hand_psnr_mask_db"] > rec["hand_psnr_mask_black_db"] + 2, (summary, rec)
    # the template with the fitted poses finds the contact region: well above chance (measured 0.13;
    # 0.32 when the paint was every point within 4 mm of the object, not the skin that touched it)
    assert summary["baseline_iou"] > 0.08


def test_more_views_give_better_contacts(demo):
    """The camera ablation: models rebuilt from 3, 6 and all 12 cameras (measured on the anatomical
    hand with refined poses: 0.057, 0.089, 0.187 IoU, 0.046, 0.088, 0.177 before the view-dependent
    colour was learnt and the centres' steps grew; on the capsule hand 0.051, 0.264, 0.330)."""
    _, summary, _ = demo
    views = [summary["views"][k] for k in ("3", "6", "12")]
    assert views[0] < views[1] < views[2], views


def demo_config(tmp_path, monkeypatch, args: list[str]) -> DemoConfig:
    """The DemoConfig that `manus-capture demo ARGS` runs with."""
    seen = []

    def run_demo(output, config, **_):
        seen.append(config)
        raise SystemExit(0)

    monkeypatch.setattr("manus_capture.commands.demo.run_demo", run_demo)
    result = CliRunner().invoke(cli, ["demo", "-o", str(tmp_path / "out"), *args])
    assert result.exit_code == 0 and len(seen) == 1, result.output
    return seen[0]


@pytest.mark.parametrize("args, steps", [([], (400, 1000)), (["--iterations", "300"], (300, 300)),
                                         (["--iterations", "300", "--hand-iterations", "500"], (300, 500))])
def test_demo_training_steps_by_model(tmp_path, monkeypatch, args, steps):
    """The object's and MANUS-Hand's steps: 400 and 1000 by default (the hand as `reconstruct hand`),
    both from --iterations, the hand's from --hand-iterations over it."""
    config = demo_config(tmp_path, monkeypatch, args)
    assert (config.object_iterations, config.hand_iterations) == steps


def test_demo_reads_no_truth_unless_an_ablation_is_named(tmp_path, monkeypatch):
    """The simulated detector and the simulator's cameras read the ground truth: only when named."""
    config = demo_config(tmp_path, monkeypatch, [])
    assert not config.simulated_keypoints and not config.true_calibration
    config = demo_config(tmp_path, monkeypatch, ["--simulated-keypoints", "--true-calibration"])
    assert config.simulated_keypoints and config.true_calibration


def test_default_keypoints_are_the_onnx_detectors(demo, tmp_path, monkeypatch):
    """`make demo` annotates with the ONNX detector on the frames, and the bones come from its keypoints
    of the hand take; annotate's cross-view step looks again where the palm detector found nothing.
    Measured on this session (12 cameras at 320x180), in brackets without the cross-view step: a
    hand found in 50 % of the grasp's views (26 %), its joints triangulated 8.2 mm (9.1) and fitted
    8.9 mm (9.4) from the truth, finger angles 9.5 deg RMS (12.0), the bones 10.8 mm (10.1) off at
    worst (on `make demo`'s session MediaPipe's landmarks span 5-9 % less than the true joints; on
    the real photos of test_keypoints_real they do not); the simulated detector's keypoints of the
    same takes are fitted 3.1 mm off, 8.4 deg (test_stages_agree_with_the_simulators_truth). The
    bounds give the detector's figures a factor 2. The hand take is detected once, though its
    keypoints give both the subject's bones and its own annotation."""
    from dataset_tools import take_keypoints

    detected = []
    original = take_keypoints.detect_take
    monkeypatch.setattr(take_keypoints, "detect_take",
                        lambda take, *a, **k: detected.append(take.path.name) or original(take, *a, **k))
    out, summary, _ = demo
    assert stage(summary, "annotate")["keypoints"] == "simulated"
    run = tmp_path / "run"
    shutil.copytree(out / "session", run / "session", ignore=shutil.ignore_patterns("subjects"))
    (run / "calib").symlink_to(out / "calib")
    figures = Demo(run, DemoConfig(), say=lambda _: None).annotate()
    assert figures["keypoints"] == "detect", figures
    assert sorted(detected) == ["01-hand", "03-grasp1", "04-canonical1"], detected
    for name in ("01-hand", "03-grasp1", "04-canonical1"):
        assert (run / "session" / name / "keypoints2d.h5").is_file(), name
    with h5py.File(run / "DATASET.h5") as f:
        attrs = f["session/03-grasp1"].attrs
        assert attrs["keypoint_source"] == "detect:mediapipe-hand+cross-view", dict(attrs)
        assert attrs["views_recovered"] > 0 and "from 01-hand" in attrs["bone_source"], dict(attrs)
        assert figures["views_recovered"] == attrs["views_recovered"], figures
    assert figures["views_with_hand"] > 0.25 and figures["fitted_mpjpe_mm"] < 18, figures
    assert figures["finger_angle_rms_deg"] < 19 and figures["bone_length_err_mm"] < 22, figures


def test_a_demo_run_again_estimates_the_bones_again(tmp_path):
    """A forced run records a new session: the subject file of the run before (which annotate would
    read instead of the hand take) goes."""
    demo = Demo(tmp_path, DemoConfig(cameras=6, resolution=(160, 90), fps=10, durations=dict.fromkeys(
        ("calibration", "hand", "object", "grasp", "canonical"), 0.1)), say=lambda _: None)
    stale = demo.session / "subjects" / "s01.json"
    stale.parent.mkdir(parents=True)
    stale.write_text("{}")
    demo.record()
    assert not stale.exists() and (demo.session / "session.toml").is_file()


@pytest.fixture(scope="module")
def second_seed(tmp_path_factory):
    """The same session with another seed (cameras, clocks and grasp drawn anew), all cameras only."""
    out = tmp_path_factory.mktemp("demo") / "seed1"
    args = [*ARGS[:ARGS.index("--views")], "--views", "all", *ARGS[ARGS.index("--iterations"):], "--seed", "1"]
    result = CliRunner().invoke(cli, ["demo", "-o", str(out), *args])
    assert result.exit_code == 0, result.output
    return json.loads((out / "summary.json").read_text())


def test_gaussian_hand_beats_the_template(demo, second_seed):
    """On the anatomical hand with refined poses, over two seeds: measured 0.187 against 0.145 (+29 %)
    and 0.218 against 0.157 (+39 %) with the view-dependent colour learnt and the centres at 7.5x
    3DGS's steps (docs/splat.md); 0.177 against 0.142 (+25 %) and 0.197 against 0.152 (+30 %)
    before, with MANUS-Hand trained on each frame's own pose fit; on the
    1-euro-filtered poses 0.160 against 0.142 (+13 %) and 0.179 against 0.157 (+14 %), when the
    margin held was 3 %; before refinement 0.125 against 0.116 and 0.144 against 0.130. On the
    capsule hand it was 0.330 against 0.321: the template's own class. docs/contacts.md has the full
    comparison."""
    for summary in (demo[1], second_seed):
        assert summary["contact_iou"] > MARGIN * summary["baseline_iou"], summary


def test_commands_on_the_demo_session(demo, tmp_path):
    """reconstruct hand (masks from segment), contacts and evaluate through the command line on
    the demo's session: the same figures as the demo's own stages, from the files alone."""
    out, summary, _ = demo
    runner = CliRunner()
    session, dataset = out / "session", tmp_path / "D.h5"
    dataset.write_bytes((out / "DATASET.h5").read_bytes())
    hand = tmp_path / "hand.safetensors"
    result = runner.invoke(cli, ["reconstruct", "hand", "--cameras", str(out / "calib"), "--take",
                                 str(session / "01-hand"), "--dataset", str(dataset), "--dataset-take",
                                 "session/01-hand", "--iterations", "60", "--poses", "6", "--empty",
                                 str(session / "00-calibration"), "-o", str(hand)])
    assert result.exit_code == 0, result.output
    assert "held-out poses" in result.output and "PSNR on the mask" in result.output
    assert load_checkpoint(hand)[2]["empty"] == str(session / "00-calibration")
    # surfels on the template by default, and the demo's too: drawn again with the blur they learnt with
    assert load_checkpoint(hand)[2]["eps2d"] == "0.05"
    assert load_checkpoint(out / "models" / "hand.safetensors")[2]["eps2d"] == "0.05"
    result = runner.invoke(cli, ["contacts", str(dataset), "--take", "session/03-grasp1", "--hand",
                                 str(out / "models" / "hand.safetensors"), "--object",
                                 str(out / "models" / "object.safetensors")])
    assert result.exit_code == 0, result.output
    # the maps went through a file beside the dataset (a long take's do not fit in memory), gone now
    assert not list(tmp_path.glob(".D.h5.*"))
    with h5py.File(dataset) as f:
        accumulated = f["session/03-grasp1/contacts/accumulated"][()]
        assert f["session/03-grasp1/contacts/instant"].shape[0] == len(f["session/03-grasp1/frame_ns"])
        assert f["session/03-grasp1/contacts/instant"].dtype == np.float16
    stage_contacts = stage(summary, "contacts")
    assert int((accumulated > 0.5).sum()) == stage_contacts["hand_gaussians_in_contact"]
    scores = tmp_path / "scores.json"
    result = runner.invoke(cli, ["evaluate", str(dataset), "--grasp", "session/03-grasp1", "--canonical",
                                 "session/04-canonical1", "--calib", str(out / "calib"), "--hand",
                                 str(out / "models" / "hand.safetensors"), "--object",
                                 str(out / "models" / "object.safetensors"), "-o", str(scores)])
    assert result.exit_code == 0, result.output
    got = json.loads(scores.read_text())
    assert abs(got["contact_iou"] - summary["contact_iou"]) < 1e-6
    assert abs(got["baseline_iou"] - summary["baseline_iou"]) < 1e-6
    # bad input: a take that is not in the dataset is named, exit code 2
    result = runner.invoke(cli, ["contacts", str(dataset), "--take", "session/nope", "--hand",
                                 str(out / "models" / "hand.safetensors"), "--object",
                                 str(out / "models" / "object.safetensors")])
    assert result.exit_code == 2 and "session/nope" in result.output


def test_refine_command_on_a_perturbed_take(demo, tmp_path):
    """`refine` through the command line on the demo's grasp take, its filtered finger angles
    perturbed by 6 deg RMS more: refinement takes them back well below the unrefined angles' own
    error, annotate's angles stay as they were, and contacts says it uses the refined ones.
    Bad input: another subject's model, and a take without masks, exit code 2 naming them."""
    out, summary, _ = demo
    runner = CliRunner()
    session, dataset, key = out / "session", tmp_path / "D.h5", "session/03-grasp1"
    dataset.write_bytes((out / "DATASET.h5").read_bytes())
    rng = np.random.default_rng(0)
    with h5py.File(dataset, "r+") as f:
        angles = f[key]["joint_angles"][()]
        perturbed = angles.copy()
        perturbed[:, 6:] += np.radians(6.0) * rng.standard_normal(angles[:, 6:].shape)
        f[key]["joint_angles"][...] = perturbed
        frame_ns = f[key]["frame_ns"][()]
    gt = GroundTruth.of_take(session / "03-grasp1")
    truth = gt.hand.joint_angles[np.clip(gt.tick_at(frame_ns), 0, len(gt.hand.joint_angles) - 1)]

    def rms(a):
        return float(np.degrees(np.sqrt(np.nanmean((a[:, 6:] - truth[:, 6:]) ** 2))))

    hand = out / "models" / "hand.safetensors"
    args = ["refine", str(session / "03-grasp1"), "--dataset", str(dataset), "--calib", str(out / "calib"),
            "--iterations", "5", "--views-per-frame", "1"]
    result = runner.invoke(cli, [*args, "--hand", str(hand)])
    assert result.exit_code == 0, result.output
    assert "frames refined" in result.output
    with h5py.File(dataset) as f:
        refined = f[key]["joint_angles_refined"][()]
        np.testing.assert_array_equal(f[key]["joint_angles"][()], perturbed)
        assert f[key]["refine/loss"].shape == (len(frame_ns),)
    # measured: the filter's angles 8.35 deg off, perturbed 10.4, refined (5 image steps, 3 views a frame) 4.95
    assert rms(perturbed) > 9.5 and rms(refined) < 0.7 * summary["finger_angle_rms_deg"], (rms(perturbed),
                                                                                             rms(refined))
    result = runner.invoke(cli, ["contacts", str(dataset), "--take", key, "--hand", str(hand), "--object",
                                 str(out / "models" / "object.safetensors")])
    assert result.exit_code == 0 and "poses from joint_angles_refined" in result.output, result.output

    gaussians, extra, meta = load_checkpoint(hand)
    extra = {**extra, "bone_lengths": extra["bone_lengths"] * 1.1}
    other = tmp_path / "other.safetensors"
    save_checkpoint(other, gaussians, kind="hand", extra=extra, metadata=meta)
    result = runner.invoke(cli, [*args, "--hand", str(other)])
    assert result.exit_code == 2, result.output
    assert str(other) in result.output and key in result.output and "another subject" in result.output
    with h5py.File(dataset, "r+") as f:
        del f[key]["masks"]
    result = runner.invoke(cli, [*args, "--hand", str(hand)])
    assert result.exit_code == 2 and "no hand and object masks" in result.output, result.output


class Recorded(api.Progress):
    """A progress callable that remembers what it was told."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, int, int | None]] = []

    def __call__(self, stage: str, done: int, total: int | None) -> None:
        self.calls.append((stage, done, total))


def test_api_record_and_sync(tmp_path):
    """record_take and sync_take on a small rig of its own, scored on the simulator's drops."""
    rig = with_sim_subject(api.make_rig("cube53", cameras=4, resolution=(160, 90), fps=20, seed=5), obj="box")
    (tmp_path / "rig.toml").write_text(rig_to_toml(rig))
    rig = api.load_rig(tmp_path / "rig.toml")
    assert isinstance(rig, api.RigConfig)
    progress = Recorded()
    result = api.record_take(rig, tmp_path / "S", "t", "grasp", 0.3, api.RecordOptions(use_leds=False),
                             progress=progress)
    assert isinstance(result, api.TakeResult) and result.status == "complete", result.reason
    assert progress.calls and progress.calls[-1][0].startswith("rec")
    take = api.Take(result.path)
    report = api.sync_take(take.path, optical=False)
    dropped = GroundTruth.of_take(take.path).frames.dropped.sum()
    assert sum(c["frames_dropped"] for c in report["cameras"].values()) == dropped
    groups = api.frame_groups(take)
    assert isinstance(groups, api.TakeGroups) and groups.path is not None  # the report's own groups
    assert groups.frame_index.shape == (len(groups.frame_ns), 4)
    api.silent("rec", 0, None)  # the default progress takes the same arguments and says nothing


def test_api_calibrate_annotate_segment(demo, tmp_path):
    """The offline stages through the api on the demo's takes, against the simulator's truth."""
    out, _, _ = demo
    session = out / "session"
    truth = GroundTruth.of_take(session / "00-calibration").cameras.rig()
    # the lenses as a lab would have them from an intrinsics session; the poses come from the tags
    lens = api.CameraRig(truth.ids, truth.K, truth.dist, np.tile(np.eye(3), (len(truth), 1, 1)),
                         np.zeros((len(truth), 3)), truth.size)
    calib = api.calibrate_rig(take=session / "00-calibration", tags=session / "tags.json", method="tags",
                              intrinsics=lens, output=tmp_path / "calib")
    assert isinstance(calib, api.RigCalibration) and not calib.partial
    rig = api.load_cameras(tmp_path / "calib")
    assert np.linalg.norm(rig.subset(truth.ids).centers - truth.centers, axis=1).max() < 0.01
    api.save_cameras(rig, tmp_path / "copy.json")
    dataset = tmp_path / "D.h5"
    canonical = session / "04-canonical1"
    summary = api.annotate([canonical], tmp_path / "calib", dataset, api.AnnotateOptions(keypoints="simulated"))
    assert isinstance(summary, api.AnnotateSummary) and not summary.failed
    data = api.read_dataset(dataset)
    ann = data[api.take_key(canonical)]
    assert isinstance(data, api.Dataset) and isinstance(ann, api.TakeAnnotation)
    hand = GroundTruth.of_take(canonical).hand
    tick = np.clip(GroundTruth.of_take(canonical).tick_at(ann.frame_ns), 0, len(hand.joints3d) - 1)
    assert np.nanmedian(np.linalg.norm(ann.fitted_joints() - hand.joints3d[tick], axis=-1)) < 0.008
    seg = api.segment_take(canonical, rig, session / "00-calibration", session / "02-object")
    assert isinstance(seg, api.Segmentation) and seg.paint is not None and seg.paint.any()
    api.write_masks(dataset, api.take_key(canonical), seg, {})
    assert api.read_dataset(dataset)[api.take_key(canonical)].attrs["mask_cameras"] == list(seg.cameras)


def test_api_keypoints_on_a_take(demo):
    out, _, _ = demo
    take = api.Take(out / "session" / "04-canonical1")
    detector = api.hand_keypoint_detector("mediapipe-hand")
    assert isinstance(detector, api.Detector)
    progress = Recorded()
    found = api.detect_take(take, detector, cameras=take.cameras[:2], progress=progress)
    assert all(isinstance(k, api.CameraKeypoints) for k in found.values())
    assert sum(len(k.keypoints) for k in found.values()) == sum(take.frame_count(c) for c in take.cameras[:2])
    assert progress.calls[-1][1] == progress.calls[-1][2]


def test_api_reconstruct_contacts_evaluate(demo, tmp_path):
    """Models on four cameras through ModelInputs, then contacts and scores with the demo's models."""
    out, summary, _ = demo
    session, rig = out / "session", api.load_cameras(out / "calib")
    inputs = api.ModelInputs.prepare(rig, out / "DATASET.h5", session / "01-hand", session / "02-object",
                                     session / "00-calibration", poses=4, object_iterations=40, hand_iterations=40)
    models = inputs.train(np.arange(0, len(rig), 3), evaluate=True)
    assert isinstance(models, api.TrainedModels) and models.metrics["hand_gaussians"] == len(models.hand)
    api.save_checkpoint(tmp_path / "object.safetensors", models.object, kind="object")
    assert torch.equal(api.load_checkpoint(tmp_path / "object.safetensors")[0].means, models.object.means)
    hand = HandGaussians.from_checkpoint(*api.load_checkpoint(out / "models" / "hand.safetensors")[:2])
    obj = api.load_checkpoint(out / "models" / "object.safetensors")[0]
    data = api.read_dataset(out / "DATASET.h5")
    angles, source = data.pose_angles("session/03-grasp1")   # refine's, as the demo used
    assert source == "joint_angles_refined"
    maps = api.model_contacts(hand, angles, obj)
    assert isinstance(maps, api.ContactMaps)
    assert int((maps.accumulated > 0.5).sum()) == stage(summary, "contacts")["hand_gaussians_in_contact"]
    dataset = tmp_path / "D.h5"
    dataset.write_bytes((out / "DATASET.h5").read_bytes())
    api.write_contacts(dataset, "session/03-grasp1", maps, {})
    pose = api.canonical_pose(data.pose_angles("session/04-canonical1")[0])
    with h5py.File(out / "DATASET.h5") as f:
        paint = f["session/04-canonical1/paint/masks"][()]
        order = [list(f["session/04-canonical1"].attrs["mask_cameras"]).index(c) for c in rig.ids]
    views = api.pick_views(paint[order], 10)
    scores, _ = api.score_contacts(hand, pose, maps.accumulated, rig, paint[order], views)
    assert isinstance(scores, api.Scores) and abs(scores.mean_iou - summary["contact_iou"]) < 1e-6
    template = api.capsule_template(data["session/03-grasp1"].bone_lengths)
    baseline, _ = api.score_contacts(template, pose, api.model_contacts(template, angles, obj).accumulated, rig,
                                     paint[order], views)
    assert abs(baseline.mean_iou - summary["baseline_iou"]) < 1e-6


def test_hand_model_trains_on_each_frames_own_fit(demo):
    """MANUS-Hand's training poses are each frame's own IK fit: the demo's hand take runs through
    its 21 poses in 2 s, and the 1-euro filter's lag moves annotate's filtered joints off the images
    by several millimetres there (8.6 mm against 3.2 on a 12-camera s03 session; the 3 mm below
    is about the fits' own error)."""
    out = demo[0]
    frames = hand_frames_from_dataset(out / "DATASET.h5", "session/01-hand")
    ann = api.read_dataset(out / "DATASET.h5")["session/01-hand"]
    truth = truth_at_groups(out / "session" / "01-hand", ann.frame_ns)
    rows = spread_frames(frames.angles, 23)     # the demo's 20 training and 3 held-out poses
    skeleton = HandSkeleton(ann.bone_lengths)
    error = {name: 1e3 * np.linalg.norm(skeleton.forward(a[rows]) - truth["joints3d"][rows], axis=-1).mean()
             for name, a in (("trained on", frames.angles), ("filtered", ann.joint_angles))}
    assert error["trained on"] < 3.5 and error["trained on"] < 0.6 * error["filtered"], error


def test_refine_in_two_processes_gives_the_angles_of_one(demo, tmp_path):
    """`refine --workers 2` on two takes: one take a task, each in its own process, and the refined
    angles are those of the run in this process, bit for bit."""
    out, _, _ = demo
    session = out / "session"
    keys = ("session/03-grasp1", "session/04-canonical1")
    refined = {}
    for name, extra in (("inline", []), ("pool", ["--workers", "2"])):
        dataset = tmp_path / f"{name}.h5"
        dataset.write_bytes((out / "DATASET.h5").read_bytes())
        result = CliRunner().invoke(cli, ["refine", str(session / "03-grasp1"), str(session / "04-canonical1"),
                                          "--dataset", str(dataset), "--calib", str(out / "calib"), "--hand",
                                          str(out / "models" / "hand.safetensors"), "--keypoint-iterations", "10",
                                          "--iterations", "1", "--threads", "1", *extra])
        assert result.exit_code == 0, result.output
        assert result.output.count("frames refined") == 2, result.output
        with h5py.File(dataset) as f:
            refined[name] = [f[key]["joint_angles_refined"][()] for key in keys]
    for a, b in zip(refined["inline"], refined["pool"]):
        np.testing.assert_array_equal(a, b)


def test_api_refine(demo, tmp_path):
    """refine_take and write_refined on the demo's canonical take: the refined angles go beside
    annotate's, and the dataset then gives them to the later stages."""
    out, _, _ = demo
    dataset, key = tmp_path / "D.h5", "session/04-canonical1"
    dataset.write_bytes((out / "DATASET.h5").read_bytes())
    hand = HandGaussians.from_checkpoint(*api.load_checkpoint(out / "models" / "hand.safetensors")[:2])
    fit = api.refine_take(dataset, key, out / "session" / "04-canonical1", api.load_cameras(out / "calib"), hand,
                          api.RefineOptions(keypoint_iterations=20, iterations=2, eps2d=0.05))
    assert isinstance(fit, api.RefineResult) and fit.frames_refined + fit.frames_diverged > 0
    api.write_refined(dataset, key, fit, {"test": True})
    angles, source = api.read_dataset(dataset).pose_angles(key)
    assert source == "joint_angles_refined" and np.array_equal(angles, fit.angles, equal_nan=True)


def test_true_calibration_ablation_feeds_the_simulators_cameras(demo, tmp_path):
    """--true-calibration, the ablation that hands the simulator's intrinsics and poses to the
    pipeline: calibrate writes the take's true cameras instead of calibrating."""
    from manus_capture.splat.takes import truth_cameras

    out, _, _ = demo
    (tmp_path / "session").symlink_to(out / "session")
    ablation = Demo(tmp_path, DemoConfig(true_calibration=True), say=lambda _: None)
    assert ablation.calibrate() == {"source": "simulator (--true-calibration)"}
    written = load_cameras(tmp_path / "calib" / "cameras.json")
    truth = truth_cameras(out / "session" / "00-calibration")
    assert written.ids == truth.ids and np.array_equal(written.K, truth.K) and np.allclose(written.t, truth.t)
    # the demo itself calibrated from the tags: its focal lengths are not the simulator's
    estimated = load_cameras(out / "calib" / "cameras.json").subset(truth.ids)
    assert not np.allclose(estimated.K, truth.K)
