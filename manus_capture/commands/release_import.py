"""`manus-capture import`: data released by others made into sessions of this toolkit (docs/datasets.md)."""

from __future__ import annotations

from pathlib import Path

import click

from dataset_tools.release.brics_import import import_release

from ..bars import Bars


@click.group()
def command() -> None:
    """Import a released dataset as a session that every later stage runs on unchanged."""


@command.command("brics")
@click.argument("src", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("-o", "--output", "session", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="The session folder to create (one take per capture of SRC).")
@click.option("--cameras", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="optim_params.txt to use (default: found in the capture, SRC or a calib* folder beside).")
@click.option("--annotations", type=click.Path(exists=True, file_okay=False, path_type=Path),
              help="Folder holding SEQ/pose_dumps/ for the captures (MANUS's annotation release).")
@click.option("--units", type=click.Choice(["m", "cm", "mm"]), default=None,
              help="Unit of the release's translations and keypoints (default: metres).")
@click.option("--kind", type=click.Choice(["calibration", "hand", "object", "grasp", "canonical"]), default=None,
              help="The takes' kind (default: from the capture's name, else hand).")
@click.option("--copy", is_flag=True, help="Copy the videos into the session (re-muxed, not re-encoded) "
                                           "instead of reading them where they lie.")
@click.option("--strict", is_flag=True, help="Fail on any camera without a video, timestamps or calibration, "
                                             "and on any frame that would be dropped.")
@click.option("--force", is_flag=True, help="Import again over takes this command imported before.")
def brics(src: Path, session: Path, cameras: Path | None, annotations: Path | None, units: str | None,
          kind: str | None, copy: bool, strict: bool, force: bool) -> None:
    """Import a MANUS-Grasps / BRICS release folder SRC (CAPTURE/synced/CAM/CAM.avi with its
    CAM_synced_files.txt, an optim_params.txt, and any pose_dumps/ and images/refined_seg/).

    Exit code 0: imported; 2: SRC is not a release, or --strict found a problem.
    """
    with Bars("cam") as bars:
        summary = import_release(src, session, cameras=cameras, annotations=annotations, units=units, copy=copy,
                                 strict=strict, kind=kind, force=force, progress=bars)
    for take in summary.takes:
        ways = sorted({c.video for c in take.cameras})
        click.echo(f"import {take.path}: {take.kind}, {len(take.cameras)} cameras, "
                   f"{sum(c.frames for c in take.cameras)} frames (videos {', '.join(ways)})"
                   + (f"; DATASET.h5: {', '.join(take.poses)}" if take.poses else ""))
        for cam in take.cameras:
            for problem in cam.problems:
                click.echo(f"  {cam.id}: {problem}", err=True)
        for line in take.left_out:
            click.echo(f"  left out: {line}", err=True)
    click.echo(f"calibration: {summary.calibration}")
    click.echo(f"next: manus-capture sync-report {session}/TAKE; annotate {session}/TAKE --calib "
               f"{summary.calibration.parent}")
