"""`manus-capture annotate`: triangulate, fit the hand skeleton and filter, into DATASET.h5."""

from __future__ import annotations

import time
from pathlib import Path

import click

from dataset_tools.annotate import AnnotateOptions, annotate
from manus_capture.bars import Bars
from manus_core.errors import AnnotateError

from .cluster import cluster_options


@click.command("annotate", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("takes", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--calib", required=True, type=click.Path(path_type=Path),
              help="The calibration: a folder with cameras.json, or any file load_cameras reads.")
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path), help="DATASET.h5 to write.")
@click.option("--keypoints", type=click.Choice(["auto", "file", "simulated", "detect"]), default="auto",
              show_default=True,
              help="2D keypoints: TAKE/keypoints2d.h5 (file), the ONNX detector (detect); auto takes the file "
                   "when the take has one, else detects. 'simulated' is an ablation on a simulated take: its "
                   "ground truth's joints with simulated detector noise, never chosen by auto.")
@click.option("--model", default="mediapipe-hand", show_default=True,
              help="Keypoint model for --keypoints detect (or auto without keypoints2d.h5).")
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default="auto", show_default=True,
              help="onnxruntime provider for detection.")
@click.option("--palm-tiles", is_flag=True,
              help="When detecting: the palm detector also looks at square tiles of each wide frame (as "
                   "`detect --palm-tiles`: small hands found more often, slower).")
@click.option("--cross-view/--no-cross-view", default=True, show_default=True,
              help="When detecting: where the palm detector found no hand in a view, look for it where the "
                   "hand the other views triangulate projects (docs/annotate.md).")
@click.option("--bones", type=click.Path(path_type=Path), default=None,
              help="A subject file (subjects/SUBJECT.json) to use for every take instead of estimating.")
@cluster_options("by take")
@click.option("--sim-noise-px", type=click.FloatRange(0), default=2.0, show_default=True,
              help="Simulated detector: Gaussian noise per axis (px).")
@click.option("--sim-outliers", type=click.FloatRange(0, 1), default=0.1, show_default=True,
              help="Simulated detector: fraction of visible joints that are outliers.")
@click.option("--sim-seed", type=int, default=0, show_default=True, help="Simulated detector: seed.")
@click.option("--threshold-px", type=click.FloatRange(0, min_open=True), default=10.0, show_default=True,
              help="Triangulation inlier threshold (px).")
@click.option("--min-cutoff", type=click.FloatRange(0, min_open=True), default=1.0, show_default=True,
              help="1-euro filter: minimum cutoff (Hz).")
@click.option("--beta", type=click.FloatRange(0), default=10.0, show_default=True,
              help="1-euro filter: speed coefficient for angles (1/rad).")
@click.option("--cameras", default=None, metavar="A,B,...",
              help="The cameras to use (each in every take and the calibration); default: every camera of a "
                   "take that the calibration has.")
@click.option("--force", is_flag=True,
              help="Recompute takes already in the output (or saved by an interrupted run) even when their inputs "
                   "are the same. Their masks, paint and contacts are kept.")
def command(takes: tuple[Path, ...], calib: Path, output: Path, keypoints: str, model: str, device: str,
            palm_tiles: bool, cross_view: bool, bones: Path | None, workers: int, scheduler: str | None,
            sim_noise_px: float, sim_outliers: float, sim_seed: int, threshold_px: float, min_cutoff: float,
            beta: float, cameras: str | None, force: bool) -> None:
    """Annotate TAKES into a dataset file: frame groups, 2D keypoints, triangulation, the subject's
    bone lengths, inverse kinematics on the 26-DOF hand, 1-euro filter (docs/annotate.md).

    Takes already in OUTPUT, or finished by an interrupted run, are kept when every input that made
    them is the same (the take's frames, calibration, cameras, keypoints, frame groups, bones,
    settings), and redone otherwise, saying why. Cameras the calibration lacks are left out. Hand
    takes of a session give the subject's bone lengths, saved as SESSION/subjects/SUBJECT.json;
    give them in the same run or annotate them first.
    """
    options = AnnotateOptions(keypoints=keypoints, model=model, device=device, palm_tiles=palm_tiles,
                              cross_view=cross_view, sim_noise_px=sim_noise_px,
                              sim_outlier_rate=sim_outliers, sim_seed=sim_seed, threshold_px=threshold_px,
                              min_cutoff=min_cutoff, beta=beta)
    chosen = [c.strip() for c in cameras.split(",") if c.strip()] if cameras is not None else None
    if chosen == []:
        raise AnnotateError(f"--cameras {cameras!r}: no camera named (give A,B,...)")
    start = time.perf_counter()
    with Bars(unit="take") as bars:
        summary = annotate(takes, calib, output, options, workers=workers, scheduler=scheduler, force=force,
                           bones=bones, cameras=chosen, progress=bars)
    elapsed = time.perf_counter() - start
    for key, cams in summary.left_out.items():
        why = "not chosen by --cameras" if chosen else f"not in the calibration {calib}"
        click.echo(f"{key}: left out camera(s) {', '.join(cams)} ({why})", err=True)
    if summary.resumed:
        click.echo(f"kept (same inputs): {', '.join(summary.resumed)}")
    for key, reasons in summary.redone.items():
        done = "redone" if key in summary.annotated else "failed to redo (its earlier annotation stays)"
        click.echo(f"{done} {key}: {'; '.join(reasons)}")
    for key, why in summary.failed.items():
        click.echo(f"failed: {key}: {why}", err=True)
    fitted = 100.0 * summary.frames_fitted / max(summary.frames, 1)
    click.echo(f"{output}: {len(summary.annotated)} takes annotated, {len(summary.resumed)} kept from before, "
               f"{len(summary.failed)} failed; {summary.frames} frames, hand fitted in {summary.frames_fitted} "
               f"({fitted:.1f}%); {elapsed:.1f} s")
    if summary.failed:
        raise AnnotateError(f"{len(summary.failed)} take(s) failed: {', '.join(summary.failed)}")
