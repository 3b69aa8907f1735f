"""The demo end to end at a small size: every stage runs on recorded simulated takes and is
scored against the simulator's truth; the report and summary.json carry the figures."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from manus_capture.cli import cli
from manus_capture.splat.checkpoint import load_checkpoint

ARGS = ["--cameras", "12", "--resolution", "320x180", "--fps", "20", "--views", "3,6,all", "--iterations", "300"]


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
    assert names == ["record", "sync", "calibrate", "annotate", "segment", "reconstruct", "contacts", "evaluate"]
    for key in ("contact_iou", "contact_f1", "baseline_iou", "baseline_f1"):
        assert 0.0 <= summary[key] <= 1.0
    assert set(summary["views"]) == {"3", "6", "12"}
    html = (out / "report.html").read_text()
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
    # 12 cameras at 320x180 seeing tags 1-2 m away: a few millimetres (the 53-camera test holds 2 mm)
    assert calib["centre_err_mm_max"] < 10 and calib["rotation_err_deg_max"] < 0.5, calib
    ann = stage(summary, "annotate")
    # 2 px detector noise at 320x180 is ~5 mm per view at 1 m; 12 views and the skeleton bring it down
    assert ann["fitted_mpjpe_mm"] < 8 and ann["bone_length_err_mm"] < 4, ann
    seg = stage(summary, "segment")
    assert seg["object_iou"] > 0.9 and seg["hand_iou"] > 0.9 and seg["paint_iou"] > 0.5, seg
    rec = stage(summary, "reconstruct")
    assert rec["hand_psnr_heldout_poses_db"] > 24 and rec["object_psnr_train_views_db"] > 28, rec
    # the template with the fitted poses finds the contact region: well above chance
    assert summary["baseline_iou"] > 0.15


def test_more_views_give_better_contacts(demo):
    """The camera ablation: models rebuilt from 3, 6 and all 12 cameras (measured: 0.051, 0.264,
    0.330 IoU with surfels; 0.0, 0.109, 0.098 with the round Gaussians before)."""
    _, summary, _ = demo
    views = [summary["views"][k] for k in ("3", "6", "12")]
    assert views[0] < views[1] < views[2], views


def test_gaussian_hand_beats_the_template(demo):
    """Measured 0.330 against 0.321. The simulated hand is capsules on the same skeleton as the
    template, within a millimetre of it for this subject, so the margin is small; it was 0.309
    against 0.321 while contact was drawn with the surfels' learned opacities (docs/contacts.md)."""
    _, summary, _ = demo
    assert summary["contact_iou"] > summary["baseline_iou"]


def test_commands_on_the_demo_session(demo, tmp_path):
    """reconstruct hand (masks from segment), contacts and evaluate through the command line on
    the demo's session: the same figures as the demo's own stages, from the files alone."""
    import h5py

    out, summary, _ = demo
    runner = CliRunner()
    session, dataset = out / "session", tmp_path / "D.h5"
    dataset.write_bytes((out / "DATASET.h5").read_bytes())
    hand = tmp_path / "hand.safetensors"
    result = runner.invoke(cli, ["reconstruct", "hand", "--cameras", str(out / "calib"), "--take",
                                 str(session / "01-hand"), "--dataset", str(dataset), "--dataset-take",
                                 "session/01-hand", "--iterations", "60", "--poses", "6", "-o", str(hand)])
    assert result.exit_code == 0, result.output
    assert "held-out poses" in result.output
    # surfels on the template by default, and the demo's too: drawn again with the blur they learnt with
    assert load_checkpoint(hand)[2]["eps2d"] == "0.05"
    assert load_checkpoint(out / "models" / "hand.safetensors")[2]["eps2d"] == "0.05"
    result = runner.invoke(cli, ["contacts", str(dataset), "--take", "session/03-grasp1", "--hand",
                                 str(out / "models" / "hand.safetensors"), "--object",
                                 str(out / "models" / "object.safetensors")])
    assert result.exit_code == 0, result.output
    with h5py.File(dataset) as f:
        accumulated = f["session/03-grasp1/contacts/accumulated"][()]
        assert f["session/03-grasp1/contacts/instant"].shape[0] == len(f["session/03-grasp1/frame_ns"])
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
