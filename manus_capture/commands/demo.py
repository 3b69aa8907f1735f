"""`manus-capture demo`: the whole pipeline on the simulated rig, scored against its truth."""

from __future__ import annotations

from pathlib import Path

import click

from manus_capture.demo import DemoConfig, run_demo
from manus_capture.report import text_table


def _views(text: str) -> tuple[int, ...]:
    try:
        values = tuple(0 if v.strip() == "all" else int(v) for v in text.split(","))
    except ValueError:
        raise click.BadParameter(f"{text!r}: expected camera counts such as 5,10,20,all") from None
    if not values or any(v < 0 for v in values):
        raise click.BadParameter(f"{text!r}: expected positive camera counts or 'all'")
    return values


@click.command("demo", context_settings={"help_option_names": ["-h", "--help"]})
@click.option("-o", "--output", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Folder for the session, calibration, dataset, models and report.")
@click.option("--cameras", type=click.IntRange(6, 53), default=24, show_default=True,
              help="Cameras of the simulated cube53 rig.")
@click.option("--resolution", default="320x180", show_default=True, help="Camera resolution WxH.")
@click.option("--fps", type=click.FloatRange(1, 120), default=30.0, show_default=True)
@click.option("--object", "obj", type=click.Choice(["mug", "box", "sphere"]), default="mug", show_default=True)
@click.option("--subject", default="s01", show_default=True,
              help="A simulated subject (s01, s02, s03) or a subject file NAME.toml (docs/simulation.md).")
@click.option("--views", "views", default="5,10,20,all", show_default=True, callback=lambda c, p, v: _views(v),
              help="Camera counts of the ablation (models rebuilt from that many cameras).")
@click.option("--iterations", type=click.IntRange(50), default=None,
              help="Training iterations of both Gaussian models.  [default: the object "
                   f"{DemoConfig.object_iterations}, MANUS-Hand {DemoConfig.hand_iterations}]")
@click.option("--hand-iterations", type=click.IntRange(50), default=None,
              help="MANUS-Hand's training iterations, over --iterations.")
@click.option("--refine-iterations", type=click.IntRange(0), default=20, show_default=True,
              help="Steps of refine's second stage (MANUS-Hand rendered into the views; docs/refine.md).")
@click.option("--true-calibration", is_flag=True, help="Use the simulator's cameras instead of calibrating.")
@click.option("--simulated-keypoints", is_flag=True,
              help="Ablation: annotate from the true joints with the simulated detector's noise and outliers "
                   "instead of the ONNX detector on the frames (reads ground_truth.h5; docs/annotate.md).")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--force", is_flag=True, help="Run again into a folder that holds a finished demo.")
def command(output: Path, cameras: int, resolution: str, fps: float, obj: str, subject: str,
            views: tuple[int, ...], iterations: int | None, hand_iterations: int | None, refine_iterations: int,
            true_calibration: bool, simulated_keypoints: bool, seed: int, force: bool) -> None:
    """Record a painted-object session on the simulated cube (calibration, hand, object, grasp and
    canonical takes), run sync reports, calibrate, annotate, segment, reconstruct, refine, contacts
    and evaluate, and print every stage's error against ground truth. Writes OUTPUT/report.html and
    OUTPUT/summary.json (contact IoU and F1 of the Gaussian hand and of the capsule baseline, and
    the camera ablation). Exit code 0 when every stage ran, 1 when one failed."""

    try:
        w, h = (int(v) for v in resolution.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"{resolution!r}: expected WxH, e.g. 320x180", param_hint="--resolution") from None
    steps = {"object_iterations": iterations, "hand_iterations": hand_iterations or iterations}
    config = DemoConfig(cameras=cameras, resolution=(w, h), fps=fps, object=obj, subject=subject, views=views,
                        refine_iterations=refine_iterations, true_calibration=true_calibration,
                        simulated_keypoints=simulated_keypoints, seed=seed,
                        **{k: v for k, v in steps.items() if v is not None})
    summary = run_demo(output, config, say=click.echo, force=force)
    click.echo(text_table(summary["stages"]))
    ablation = ", ".join(f"{k} cams {v:.3f}" for k, v in summary["views"].items())
    click.echo(f"demo: contact IoU {summary['contact_iou']:.3f} (F1 {summary['contact_f1']:.3f}), capsule baseline "
               f"IoU {summary['baseline_iou']:.3f} (F1 {summary['baseline_f1']:.3f}); ablation {ablation}; "
               f"{summary['seconds']:.0f} s -> {output / 'report.html'}")
