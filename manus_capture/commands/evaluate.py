"""`manus-capture evaluate`: estimated contacts against the green paint, and the capsule baseline."""

from __future__ import annotations

import json
import time
from pathlib import Path

import click
import h5py

from dataset_tools.calibration.formats import load_cameras
from manus_capture.builder import ModelInputs
from manus_capture.contacts import model_contacts
from manus_capture.evaluate import canonical_pose, pick_views, score_contacts, spread_cameras
from manus_capture.splat.checkpoint import load_checkpoint
from manus_capture.splat.hand import HandGaussians
from manus_capture.template import capsule_template
from manus_core.dataset import read_dataset
from manus_core.errors import EvaluateError
from manus_core.fileio import write_atomic


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
def command(dataset: Path, grasp: str, canonical: str, calib: Path, hand_path: Path, object_path: Path,
            gt_views: int, views: tuple[int, ...], hand_take: Path | None, object_take: Path | None,
            background: Path | None, iterations: int, tau: float, threshold: float,
            output: Path | None) -> None:
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
    grasp_ann, canonical_ann = data[grasp], data[canonical]
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
    pose = canonical_pose(canonical_ann.joint_angles)
    angles = grasp_ann.joint_angles
    gaussians, extra, _ = load_checkpoint(hand_path)
    hand = HandGaussians.from_checkpoint(gaussians, extra)
    obj, _, _ = load_checkpoint(object_path)
    chosen = pick_views(paint, gt_views)

    def score(model, gaussians_obj):
        maps = model_contacts(model, angles, gaussians_obj, tau)
        return score_contacts(model, pose, maps.accumulated, rig, paint, chosen, threshold)[0]

    ours = score(hand, obj)
    baseline = score(capsule_template(grasp_ann.bone_lengths), obj)
    result = {"contact_iou": ours.mean_iou, "contact_f1": ours.mean_f1, "baseline_iou": baseline.mean_iou,
              "baseline_f1": baseline.mean_f1, "gaussian": ours.to_json(), "baseline": baseline.to_json(),
              "tau_m": tau, "threshold": threshold}
    if views:
        if hand_take is None or object_take is None or background is None:
            raise click.UsageError("--views needs --hand-take, --object-take and --background")

        inputs = ModelInputs.prepare(rig, dataset, hand_take, object_take, background,
                                     object_iterations=iterations, hand_iterations=iterations)
        result["views"] = {}
        for n in views:
            count = len(rig) if n == 0 else min(n, len(rig))
            click.echo(f"ablation: models from {count} cameras ...", err=True)
            models = inputs.train(spread_cameras(rig, count))
            result["views"][str(count)] = score(models.hand, models.object).mean_iou
    if output is not None:
        write_atomic(output, json.dumps(result, indent=2).encode())
    ablation = "".join(f"; {k} cameras IoU {v:.3f}" for k, v in result.get("views", {}).items())
    click.echo(f"evaluate: {grasp} on {len(chosen)} views: IoU {ours.mean_iou:.3f}, F1 {ours.mean_f1:.3f}; "
               f"capsule baseline IoU {baseline.mean_iou:.3f}, F1 {baseline.mean_f1:.3f}{ablation} "
               f"({time.perf_counter() - start:.1f} s)")
