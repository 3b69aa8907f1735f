"""`manus-capture evaluate`: estimated contacts against the green paint, and the capsule baseline."""

from __future__ import annotations

import json
import time
from pathlib import Path

import click
import h5py

from dataset_tools.calibration.formats import load_cameras
from manus_capture.bars import Bars
from manus_capture.builder import ModelInputs
from manus_capture.evaluate import canonical_pose, pick_views
from manus_capture.evaluate_tasks import Ablation, Checkpoints, ScoreTask, Scoring, scores_in_tasks
from manus_capture.splat.checkpoint import load_checkpoint
from manus_capture.torch_threads import TRAIN_THREADS
from manus_core.dataset import read_dataset
from manus_core.errors import EvaluateError
from manus_core.fileio import write_atomic

from .cluster import cluster_options


def _counts(ctx, param, values: tuple[str, ...]) -> tuple[int, ...]:
    out = []
    for v in values:
        if v == "all":
            out.append(0)
        elif v.isdigit() and int(v) >= 2:
            out.append(int(v))
        else:
            raise click.BadParameter(f"{v!r}: a camera count of at least 2, or 'all'")
    return tuple(out)


@click.command("evaluate", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("dataset", type=click.Path(path_type=Path, exists=True, dir_okay=False))
@click.option("--grasp", required=True, metavar="SESSION/TAKE", help="The grasp take in DATASET.")
@click.option("--canonical", required=True, metavar="SESSION/TAKE",
              help="The canonical take after it, segmented (paint/masks) and annotated.")
@click.option("--calib", required=True, type=click.Path(path_type=Path), help="The calibration.")
@click.option("--hand", "hand_path", required=True, type=click.Path(path_type=Path, exists=True, dir_okay=False),
              help="MANUS-Hand checkpoint.")
@click.option("--object", "object_path", required=True, type=click.Path(path_type=Path, exists=True, dir_okay=False),
              help="Object checkpoint.")
@click.option("--gt-views", type=click.IntRange(1), default=10, show_default=True,
              help="Ground-truth views: those showing the most paint.")
@click.option("--views", "views", multiple=True, callback=_counts, metavar="N",
              help="Camera ablation: rebuild both models from N cameras (repeat: --views 5 --views 10 "
                   "--views all); needs --hand-take, --object-take and --background.")
@click.option("--hand-take", type=click.Path(path_type=Path, file_okay=False), default=None)
@click.option("--object-take", type=click.Path(path_type=Path, file_okay=False), default=None)
@click.option("--background", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="The empty-cube take, for the masks of the ablation's models.")
@click.option("--iterations", type=click.IntRange(1), default=400, show_default=True,
              help="Training iterations of the ablation's models.")
@click.option("--tau", type=click.FloatRange(0, min_open=True), default=0.004, show_default=True)
@click.option("--threshold", type=click.FloatRange(0, 1), default=0.5, show_default=True,
              help="Rendered contact value counted as contact.")
@click.option("-o", "--output", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="scores.json (default: print only).")
@cluster_options("into one task per model scored: the Gaussian hand, the baseline, each --views count")
@click.option("--threads", type=click.IntRange(1), default=TRAIN_THREADS,
              help="Torch threads of a task (default: this machine's cores); the ablation's models (and so its "
                   "scores) depend on it, not on where the task runs.")
def command(dataset: Path, grasp: str, canonical: str, calib: Path, hand_path: Path, object_path: Path,
            gt_views: int, views: tuple[int, ...], hand_take: Path | None, object_take: Path | None,
            background: Path | None, iterations: int, tau: float, threshold: float,
            output: Path | None, workers: int, scheduler: str | None, threads: int) -> None:
    """Score the accumulated contact of GRASP against the paint seen in CANONICAL: the contact is
    carried onto the hand in the canonical pose, rendered into the ground-truth views, thresholded
    and compared with the paint masks (IoU and F1 per view, as in the MANUS contact table). The
    capsule-template baseline is scored the same way. Exit code 2 on unusable input."""
    start = time.perf_counter()
    data = read_dataset(dataset)
    for key in (grasp, canonical):
        if key not in data:
            raise EvaluateError(f"{dataset}: no take {key!r} (takes: {', '.join(data.takes) or 'none'})")
    # DatasetError, one line naming the take, for a take without annotation
    grasp_ann = data[grasp]
    with h5py.File(dataset, "r") as f:
        if "paint/masks" not in f[canonical]:
            raise EvaluateError(f"{dataset}: take {canonical} has no paint/masks (run segment on it first)")
        paint = f[canonical]["paint/masks"][()]
        mask_cams = [c.decode() if isinstance(c, bytes) else str(c) for c in f[canonical].attrs["mask_cameras"]]
    other = data.recording_differences(canonical, "segment")
    if other:
        raise EvaluateError(f"{dataset}: take {canonical}: its paint masks and its annotation are of different "
                            f"recordings ({'; '.join(other)}); redo whichever ran before the take was recorded again")
    calibrated = load_cameras(calib)
    used = [c for c in mask_cams if c in calibrated.ids]
    if len(used) < len(mask_cams):
        click.echo(f"note: cameras {', '.join(c for c in mask_cams if c not in used)} of {canonical}'s paint masks "
                   f"are not in {calib}: left out", err=True)
    if not used:
        raise EvaluateError(f"{calib}: has none of the cameras of {canonical}'s paint masks ({', '.join(mask_cams)})")
    rig = calibrated.subset(used)
    paint = paint[[mask_cams.index(c) for c in used]]
    if views and (hand_take is None or object_take is None or background is None):
        raise click.UsageError("--views needs --hand-take, --object-take and --background")
    for path in (hand_path, object_path):
        load_checkpoint(path)   # a broken checkpoint stops us now, not after the ablation's inputs
    grasp_angles, grasp_source = data.pose_angles(grasp)
    canonical_angles, canonical_source = data.pose_angles(canonical)
    click.echo(f"evaluate: poses of {grasp} from {grasp_source}, of {canonical} from {canonical_source}", err=True)
    scoring = Scoring(grasp_angles, canonical_pose(canonical_angles), rig, paint, pick_views(paint, gt_views), tau,
                      threshold)
    # the tasks' paths are absolute: a worker runs elsewhere
    hand, obj = str(hand_path.resolve()), str(object_path.resolve())
    models = {"gaussian": Checkpoints(obj, hand), "baseline": Checkpoints(obj, template_bones=grasp_ann.bone_lengths)}
    counts = [str(c) for c in dict.fromkeys(len(rig) if n == 0 else min(n, len(rig)) for n in views)]
    if counts:
        inputs = ModelInputs.prepare(rig, dataset, hand_take.resolve(), object_take.resolve(), background,
                                     object_iterations=iterations, hand_iterations=iterations)
        models.update((c, Ablation(inputs, int(c))) for c in counts)
    scores = {}
    with Bars(unit="model") as bars:
        bars("evaluate", 0, len(models))
        tasks = [ScoreTask(name, how, scoring, threads) for name, how in models.items()]
        for task, out in scores_in_tasks(grasp, tasks, workers, scheduler):
            scores[task.name] = out
            bars("evaluate", len(scores), len(models))
    ours, baseline = scores.pop("gaussian"), scores.pop("baseline")
    result = {"contact_iou": ours.mean_iou, "contact_f1": ours.mean_f1, "baseline_iou": baseline.mean_iou,
              "baseline_f1": baseline.mean_f1, "gaussian": ours.to_json(), "baseline": baseline.to_json(),
              "tau_m": tau, "threshold": threshold, "angles": {grasp: grasp_source, canonical: canonical_source}}
    if counts:
        result["views"] = {c: scores[c].mean_iou for c in counts}
    if output is not None:
        write_atomic(output, json.dumps(result, indent=2).encode())
    ablation = "".join(f"; {k} cameras IoU {v:.3f}" for k, v in result.get("views", {}).items())
    click.echo(f"evaluate: {grasp} on {len(scoring.views)} views: IoU {ours.mean_iou:.3f}, F1 {ours.mean_f1:.3f}; "
               f"capsule baseline IoU {baseline.mean_iou:.3f}, F1 {baseline.mean_f1:.3f}{ablation} "
               f"({time.perf_counter() - start:.1f} s)")
