"""`manus-capture segment`: hand and object masks, and green-paint masks, into DATASET.h5."""

from __future__ import annotations

import time
from pathlib import Path

import click
import h5py
import numpy as np

from dataset_tools.calibration.formats import load_cameras
from dataset_tools.segmentation.groups import GROUPS_PER_TASK
from dataset_tools.segmentation.takes import (
    Segmentation,
    segment_inputs,
    segment_take,
    stale_masks,
    take_cameras,
    write_masks,
    write_overlays,
)
from manus_capture.bars import Bars
from manus_core.cameras import CameraRig
from manus_core.dataset import read_dataset, take_key
from manus_core.errors import SegmentationError
from manus_core.provenance import provenance_attrs
from manus_core.take import Take

from .cluster import cluster_options


@click.command("segment", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("take", type=click.Path(path_type=Path))
@click.option("--calib", required=True, type=click.Path(path_type=Path),
              help="The calibration: a folder with cameras.json, or any file load_cameras reads.")
@click.option("--background", "background", type=click.Path(path_type=Path), default=None,
              help="A take of the empty cube (the calibration take) for the per-camera backgrounds; "
                   "needed unless --masks is given.")
@click.option("--masks", type=click.Path(path_type=Path), default=None,
              help="Masks made by another tool, used instead of segmenting: MASKS/hand/CAM/FRAME.png and "
                   "MASKS/object/CAM/FRAME.png (FRAME: the camera's frame index, 6 digits; nonzero = foreground).")
@click.option("--object-take", type=click.Path(path_type=Path), default=None,
              help="The object-only take: the object's colour, and the paint colour of a painted object.")
@click.option("--swatch", default=None, metavar="B,G,R", help="The paint colour, instead of the object take's.")
@click.option("--cameras", "cameras", default=None, metavar="A,B,...",
              help="Only these cameras (default: every camera of the take that the calibration has).")
@click.option("--every", type=click.IntRange(1), default=1, show_default=True, help="Segment every N-th frame group.")
@click.option("--overlays", type=click.Path(path_type=Path), default=None, help="Write PNG overlays into this folder.")
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path), help="DATASET.h5 to add the masks to.")
@cluster_options("into ranges of frame groups")
@click.option("--groups-per-task", type=click.IntRange(1), default=GROUPS_PER_TASK, show_default=True,
              help="Frame groups per task.")
@click.option("--force", is_flag=True, help="Redo the take's masks even when those in DATASET.h5 are current.")
def command(take: Path, calib: Path, background: Path | None, masks: Path | None, object_take: Path | None,
            swatch: str | None, cameras: str | None, every: int, overlays: Path | None, output: Path,
            workers: int, scheduler: str | None, groups_per_task: int, force: bool) -> None:
    """Segment TAKE: hand and object masks per view and frame group (background, colour, multi-view
    consistency) and, for a canonical take, the green paint on the hand (docs/segmentation.md).
    Masks of the take already in DATASET.h5 are kept when they were made from the same inputs,
    and redone (saying why) when not."""
    start = time.perf_counter()
    colour = None
    if swatch is not None:
        try:
            colour = [float(v) for v in swatch.split(",")]
            if len(colour) != 3:
                raise ValueError
        except ValueError:
            raise SegmentationError(f"--swatch {swatch!r}: expected B,G,R") from None
    if not calib.exists():
        raise SegmentationError(f"{calib}: no such calibration")
    rig = load_cameras(calib)
    opened, key = Take(take), take_key(take)
    wanted = None if cameras is None else [c.strip() for c in cameras.split(",") if c.strip()]
    cams = take_cameras(opened, rig, wanted)
    inputs = segment_inputs(opened, rig, cams, background, object_take, colour, every, masks)
    stale = stale_masks(output, key, inputs)
    if stale == [] and not force:
        click.echo(f"kept (same inputs): the masks of {key} in {output} (--force redoes them)")
        return
    # the masks go to a file beside DATASET.h5 as they are made: a long take's are larger than memory
    with Bars(unit="group") as bars:
        result = segment_take(take, rig, background, object_take, colour, every, progress=bars, masks=masks,
                              cameras=cams, workers=workers, scheduler=scheduler, groups_per_task=groups_per_task,
                              masks_file=output.with_name(f".{output.name}.{key.replace('/', '-')}.masks.h5"))
    try:
        groups = len(result.frame_ns)
        arrays, surface = _paint_on_surface(output, key, rig, result, inputs)
        write_masks(output, key, result, {"segmentation_calibration": str(calib),
                                          "segmentation_background": str(background or ""),
                                          "segmentation_masks": str(masks or ""),
                                          **provenance_attrs("segment", inputs)}, arrays)
        if stale is not None:
            click.echo(f"redone the masks of {key}: {'; '.join(stale or ['--force'])}")
        if overlays is not None:
            write_overlays(overlays, opened, result)
    finally:
        result.close()
    for message in result.report["warnings"]:
        click.echo(f"warning: {message}", err=True)
    paint = "" if result.paint is None else f", paint in {int((result.paint.sum(axis=(1, 2)) > 0).sum())} views"
    click.echo(f"segment: {groups} groups x {len(result.cameras)} cameras{paint}{surface} -> {output} "
               f"({len(result.report['warnings'])} warnings, {time.perf_counter() - start:.1f} s)")


def _paint_on_surface(output: Path, key: str, rig: CameraRig, result: Segmentation,
                      inputs: dict) -> tuple[dict[str, np.ndarray], str]:
    """The paint's contact value per hand surface point, when DATASET.h5 holds annotate's poses
    of this recording of the take; returns the arrays and the summary line's part about them."""
    if result.paint is None:
        return {}, ""
    # here, not at the top: the template poses its points with torch, whose import (1.4 s, 220 MB)
    # only a canonical take's paint needs
    from manus_capture.paint_contact import paint_on_surface
    dataset = read_dataset(output) if output.exists() else None
    if dataset is None or key not in dataset or "annotate" not in dataset.stages(key):
        click.echo(f"note: {output} has no poses of {key} (run annotate first): no contact per surface point",
                   err=True)
        return {}, ""
    other = dataset.recording_differences(key, "segment", inputs)
    if other:
        click.echo(f"note: {output}: the poses of {key} are of another recording ({'; '.join(other)}): no contact "
                   "per surface point (annotate the take again)", err=True)
        return {}, ""
    with h5py.File(output, "r") as f:
        group = f[key]
        frame_ns, angles, bones = group["frame_ns"][()], group["joint_angles"][()], group["bone_lengths"][()]
    t = result.paint_group
    at = np.flatnonzero(frame_ns == result.frame_ns[t])
    if not len(at) or not np.isfinite(angles[at[0]]).all():
        click.echo(f"note: no fitted pose for the paint's frame group of {key}: no contact per surface point", err=True)
        return {}, ""
    arrays = paint_on_surface(rig.subset(result.cameras), result.paint, result.hand[t], angles[at[0]], bones)
    painted = int((arrays["paint/contact"] > 0.5).sum())
    return arrays, f", paint on {painted} of {int((arrays['paint/voters'] > 0).sum())} seen surface points"
