"""`manus-capture segment`: hand and object masks, and green-paint masks, into DATASET.h5."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import click


@click.command("segment", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("take", type=click.Path(path_type=Path))
@click.option("--calib", required=True, type=click.Path(path_type=Path),
              help="The calibration: a folder with cameras.json, or any file load_cameras reads.")
@click.option("--background", "background", required=True, type=click.Path(path_type=Path),
              help="A take of the empty cube (the calibration take) for the per-camera backgrounds.")
@click.option("--object-take", type=click.Path(path_type=Path), default=None,
              help="The object-only take: the object's colour, and the paint colour of a painted object.")
@click.option("--swatch", default=None, metavar="B,G,R", help="The paint colour, instead of the object take's.")
@click.option("--every", type=click.IntRange(1), default=1, show_default=True, help="Segment every N-th frame group.")
@click.option("--overlays", type=click.Path(path_type=Path), default=None, help="Write PNG overlays into this folder.")
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path), help="DATASET.h5 to add the masks to.")
@click.option("--force", is_flag=True, help="Replace the take's masks if DATASET.h5 already has them.")
def command(take: Path, calib: Path, background: Path, object_take: Path | None, swatch: str | None, every: int,
            overlays: Path | None, output: Path, force: bool) -> None:
    """Segment TAKE: hand and object masks per view and frame group (background, colour, multi-view
    consistency) and, for a canonical take, the green paint on the hand (docs/segmentation.md)."""
    from tqdm import tqdm

    from dataset_tools.annotate import take_key
    from dataset_tools.calibration.formats import load_cameras
    from dataset_tools.segmentation.background import SegmentationError
    from dataset_tools.segmentation.takes import check_output, segment_take, write_masks, write_overlays
    from dataset_tools.take import Take

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
    check_output(output, take_key(take), force)
    with tqdm(desc="segment", unit="group", file=sys.stderr) as bar:
        result = segment_take(take, rig, background, object_take, colour, every, progress=bar.update)
        groups = len(result["frame_ns"])
    write_masks(output, take_key(take), result, {"segmentation_calibration": str(calib),
                                                 "segmentation_background": str(background)})
    if overlays is not None:
        write_overlays(overlays, Take(take), result)
    for message in result["report"]["warnings"]:
        click.echo(f"warning: {message}", err=True)
    paint = "" if result["paint"] is None else f", paint in {int((result['paint'].sum(axis=(1, 2)) > 0).sum())} views"
    click.echo(f"segment: {groups} groups x {len(result['cameras'])} cameras{paint} -> {output} "
               f"({len(result['report']['warnings'])} warnings, {time.perf_counter() - start:.1f} s)")
