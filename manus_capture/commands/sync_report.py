"""`manus-capture sync-report TAKE [--force]`: validate the synchronization of a recorded take."""

from __future__ import annotations

from pathlib import Path

import click

from dataset_tools.sync import SyncSettings, refuse_overwrite, sync_take, take_state
from manus_capture.bars import Bars
from manus_core.take import Take


@click.command("sync-report", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("take", type=click.Path(path_type=Path))
@click.option("--force", is_flag=True, help="Replace an existing sync_report.json/.md.")
@click.option("--tolerance-ms", type=click.FloatRange(min=0, min_open=True), default=3.0, show_default=True,
              help="Exposures of a frame group should lie within this (95th percentile); free-running "
                   "cameras: above the floor their frame phases set.")
@click.option("--max-drop-pct", type=click.FloatRange(min=0), default=1.0, show_default=True,
              help="Largest share of dropped frames a camera may have.")
@click.option("--optical/--no-optical", default=True, show_default=True,
              help="Check the timestamps against the LED flashes in take.json's LED log.")
def command(take: Path, force: bool, tolerance_ms: float, max_drop_pct: float, optical: bool) -> None:
    """Recompute TAKE/sync_report.json, sync_report.md, sync_timeline.png and frame_groups.npz.

    Per camera: clock offset and drift (robust fit of device to host time), drops from sequence
    gaps, timestamp faults, frame-interval jitter. Per take: frame groups on the nominal ticks,
    the exposure spread within them, the LED optical check; the take's status, each video's
    frame count against frames.csv and take.json, and rows of unknown cameras; a verdict. The
    frame groups are saved beside the report: annotate and segment work on them. Exit code 1 when
    the verdict is fail. See docs/sync.md.
    """
    tk = Take(take)
    refuse_overwrite(tk.path, force)
    settings = SyncSettings(tolerance_ms=tolerance_ms, max_drop_pct=max_drop_pct)
    with Bars(unit="camera") as bars:
        report = sync_take(tk.path, force=force, optical=optical, settings=settings, progress=bars)
    echo_report(report, tk.path, "sync-report")
    if report["verdict"] != "pass":
        click.get_current_context().exit(1)


def echo_report(report: dict, take: Path, label: str) -> None:
    """A sync report as the CLI shows it: each reason and note on stderr, then one verdict line
    `LABEL: TAKE: pass|fail (...) -> TAKE/sync_report.json` (sync-report, and record after a take)."""
    sp = report["spread_ms"]
    dropped = sum(c["frames_dropped"] for c in report["cameras"].values())
    spread = "n/a" if sp["p95"] is None else f"{sp['p95']:.3f} ms"
    if report["sync"] == "free-run" and report["spread_floor_ms"] is not None:
        spread += f" (phase floor {report['spread_floor_ms']:.3f} ms)"
    state = take_state(report["take_status"])
    for reason in report["reasons"]:
        click.echo(f"  fail: {reason}", err=True)
    if report["sync"] == "free-run" and report["tolerance_met"] is False:
        click.echo(f"  note: free-running cameras cannot be grouped tighter than their phases allow; exposures "
                   f"within {report['settings']['tolerance_ms']:g} ms need a hardware trigger (docs/sync.md)", err=True)
    click.echo(f"{label}: {take.name}: {report['verdict']} ("
               f"{state + ', ' if state else ''}{len(report['cameras'])} cameras, "
               f"{report['groups']} groups, {report['complete_groups']} complete, spread p95 {spread}, "
               f"{dropped} drops) -> {take / 'sync_report.json'}")
