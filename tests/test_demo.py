"""The demo end to end at a small size: every stage runs on recorded simulated takes and is
scored against the simulator's truth; the report and summary.json carry the figures."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from manus_capture.cli import cli

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


@pytest.mark.xfail(strict=True, reason="Gaussian models trained for 300 CPU iterations hold their centres "
                                       "millimetres inside the surface they draw; their contacts fall short "
                                       "of the capsule template (docs/contacts.md)")
def test_gaussian_hand_beats_the_template_and_more_views_help(demo):
    _, summary, _ = demo
    views = [summary["views"][k] for k in ("3", "6", "12")]
    assert summary["contact_iou"] > summary["baseline_iou"]
    assert views[0] < views[1] < views[2]
