"""`manus-capture export`: takes in the layouts other tools read (docs/datasets.md)."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from dataset_tools.calibration.formats import load_cameras
from dataset_tools.release.brics_export import dataset_masks, export_release
from dataset_tools.release.nerfstudio import write_frame_group
from dataset_tools.sync import frame_groups
from manus_core.dataset import take_key
from manus_core.errors import InputError
from manus_core.take import Take

from ..bars import Bars


@click.group()
def command() -> None:
    """Export takes for other tools: MANUS's release layout, nerfstudio and COLMAP."""


@command.command("brics")
@click.argument("takes", nargs=-1, required=True, type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--calib", required=True, type=click.Path(exists=True, path_type=Path),
              help="The calibration folder (or its cameras.json).")
@click.option("--dataset", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="DATASET.h5 with the takes' annotations and masks (default: SESSION/DATASET.h5 if there).")
@click.option("-o", "--output", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="The release folder to write.")
@click.option("--force", is_flag=True, help="Replace a non-empty output folder.")
def brics(takes: tuple[Path, ...], calib: Path, dataset: Path | None, output: Path, force: bool) -> None:
    """Write TAKES in the MANUS-Grasps / BRICS release layout: optim_params.txt, synced MJPEG AVIs
    with their timestamp files, pose_dumps/ JSON, RGBA masks and the hand HDF5 with crops.

    Exit code 0: written; 2: bad input (nothing is left under OUTPUT); 1: the disk failed.
    """
    if dataset is None:
        found = takes[0].resolve().parent / "DATASET.h5"
        dataset = found if found.is_file() else None
    with Bars("cam") as bars:
        done = export_release(list(takes), calib, output, dataset=dataset, force=force, progress=bars)
    for e in done:
        left = f", {e.left_out_groups} frame groups without every camera left out" if e.left_out_groups else ""
        click.echo(f"export {e.take} -> {e.capture}: {e.frames} frames{left} ({', '.join(e.parts)})")


@command.command("nerfstudio")
@click.argument("take", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--calib", required=True, type=click.Path(exists=True, path_type=Path),
              help="The calibration folder (or its cameras.json).")
@click.option("--group", default=0, show_default=True,
              help="The frame group to export (as the sync report numbers them).")
@click.option("--dataset", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="DATASET.h5 whose masks of that group become mask_path (default: SESSION/DATASET.h5 if there).")
@click.option("--masks", "which", type=click.Choice(["both", "hand", "object", "none"]), default="both",
              show_default=True, help="Which of segment's masks is the foreground.")
@click.option("-o", "--output", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="The folder to write (images/, masks/, transforms.json, sparse/0/).")
@click.option("--force", is_flag=True, help="Write into a non-empty output folder.")
def nerfstudio(take: Path, calib: Path, group: int, dataset: Path | None, which: str, output: Path,
               force: bool) -> None:
    """Write one frame group of TAKE as nerfstudio's transforms.json and a COLMAP model, so that
    nerfstudio's and gsplat's trainers read it as it is.

    Exit code 0: written; 2: bad input.
    """
    tk = Take(take)
    rig = load_cameras(calib)
    masks = None
    if dataset is None and (take.resolve().parent / "DATASET.h5").is_file():
        dataset = take.resolve().parent / "DATASET.h5"
    if dataset is not None and which != "none":
        groups = frame_groups(tk)
        if not 0 <= group < len(groups.frame_ns):
            raise InputError(f"{take}: no frame group {group}: the take has {len(groups.frame_ns)} frame groups")
        cams = [c for c, k in zip(groups.cameras, groups.frame_index[group]) if c in rig.ids and k >= 0]
        found = dataset_masks(dataset, take_key(take), groups.frame_ns[[group]], cams)
        if found is None or not found["present"][0]:
            raise InputError(f"{dataset}: no masks of take {take_key(take)} for frame group {group} "
                             "(segment it with --every 1, or pass --masks none)")
        parts = ("hand", "object") if which == "both" else (which,)
        masks = {c: np.logical_or.reduce([found[p][0, i] for p in parts]) for i, c in enumerate(cams)}
    with Bars("cam") as bars:
        path = write_frame_group(tk, rig, group, output, masks=masks, force=force, progress=bars)
    click.echo(f"export {take} group {group} -> {path}" + (f" (masks: {which})" if masks is not None else ""))
