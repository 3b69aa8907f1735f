"""`manus-capture refine`: joint angles fitted to the images through MANUS-Hand, into DATASET.h5."""

from __future__ import annotations

import hashlib
import time
from dataclasses import asdict
from pathlib import Path

import click
import numpy as np

from dataset_tools.calibration.formats import load_cameras
from manus_capture.bars import Bars
from manus_capture.refine import RefineOptions, write_refined
from manus_capture.refine_tasks import RefineTask, refine_in_tasks
from manus_capture.splat.checkpoint import load_checkpoint
from manus_capture.splat.hand import HandGaussians
from manus_capture.torch_threads import TRAIN_THREADS
from manus_core.dataset import read_dataset, take_key
from manus_core.errors import RefineInputError

from .cluster import cluster_options

DEFAULTS = RefineOptions()


@click.command("refine", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("takes", nargs=-1, required=True, type=click.Path(path_type=Path, exists=True, file_okay=False))
@click.option("--dataset", required=True, type=click.Path(path_type=Path, exists=True, dir_okay=False),
              help="DATASET.h5 with the takes' annotation and masks (annotate, segment).")
@click.option("--calib", required=True, type=click.Path(path_type=Path),
              help="The calibration: a folder with cameras.json, or any file load_cameras reads.")
@click.option("--hand", "hand_path", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="The subject's MANUS-Hand checkpoint (reconstruct hand); required.")
@click.option("--keypoint-iterations", type=click.IntRange(0), default=DEFAULTS.keypoint_iterations,
              show_default=True, help="Steps on the keypoint and smoothness terms alone.")
@click.option("--iterations", type=click.IntRange(0), default=DEFAULTS.iterations, show_default=True,
              help="Steps on every term (rendering MANUS-Hand).")
@click.option("--views-per-frame", type=click.IntRange(1), default=DEFAULTS.views_per_frame, show_default=True,
              help="Views rendered per frame and step.")
@click.option("--scale", type=click.FloatRange(0, 1, min_open=True), default=1.0, show_default=True,
              help="Reduce the images before the windows around the hand are cut.")
@click.option("--threads", type=click.IntRange(1), default=TRAIN_THREADS, show_default=True,
              help="Torch threads of each take's refinement (the same wherever it runs).")
@cluster_options("one take a task")
def command(takes: tuple[Path, ...], dataset: Path, calib: Path, hand_path: Path | None, keypoint_iterations: int,
            iterations: int, views_per_frame: int, scale: float, threads: int, workers: int,
            scheduler: str | None) -> None:
    """Refine the joint angles of TAKES (docs/refine.md): every frame's pose is fitted to the images
    by rendering MANUS-Hand into every view, with the keypoints and a smoothness term. Writes
    joint_angles_refined and the per-frame loss beside annotate's angles, which stay as they are;
    contacts and evaluate then use the refined angles. Frames where refinement made the loss
    worse keep their unrefined angles and are counted."""
    if hand_path is None or not hand_path.is_file():
        raise RefineInputError(f"refine {', '.join(map(str, takes))}: needs the subject's MANUS-Hand model, --hand "
                               f"{hand_path or 'MODEL'} {'is no file' if hand_path else 'not given'} "
                               "(make one with manus-capture reconstruct hand)")
    gaussians, extra, meta = load_checkpoint(hand_path)
    if meta.get("kind") != "hand":
        raise RefineInputError(f"--hand {hand_path}: a {meta.get('kind')!r} checkpoint, not a hand model")
    model = HandGaussians.from_checkpoint(gaussians, extra)
    options = RefineOptions(keypoint_iterations=keypoint_iterations, iterations=iterations,
                            views_per_frame=views_per_frame, scale=scale, eps2d=float(meta.get("eps2d", 0.3)))
    rig = load_cameras(calib)
    data = read_dataset(dataset)
    keys = [take_key(t) for t in takes]
    missing = [k for k in keys if k not in data.annotated]
    if missing:
        raise RefineInputError(f"{dataset}: no annotation of {', '.join(missing)} (run annotate on it first)")
    model_sha = hashlib.sha256(hand_path.read_bytes()).hexdigest()
    tasks = [RefineTask(str(dataset.resolve()), key, str(take.resolve()), rig, model, str(hand_path), options, threads)
             for take, key in zip(takes, keys)]
    start = time.perf_counter()
    with Bars(unit="step") as bars:
        for task, result in refine_in_tasks(tasks, workers, scheduler, bars):
            annotation = data.provenance(task.key, "annotate") or {}
            write_refined(dataset, task.key, result, {"take": annotation.get("take"), "hand_model_sha256": model_sha,
                                                      "options": asdict(options)})
            loss0, loss1 = np.nanmean(result.loss_initial), np.nanmean(result.loss)
            click.echo(f"refine: {task.key}: {result.frames_refined} frames refined, {result.frames_diverged} "
                       f"diverged (kept unrefined), {result.views} views; loss {loss0:.4f} -> {loss1:.4f} "
                       f"({time.perf_counter() - start:.1f} s) -> {dataset}")
