"""`manus-capture record`: one take from every camera of the rig (docs/recording.md)."""

from __future__ import annotations

import contextlib
import os
import signal
from collections.abc import Iterator
from pathlib import Path

import click

from manus_core.rig_config import load_rig
from manus_core.session import TAKE_KINDS as KINDS
from rig.record import RecordOptions, StopFlag, TakeResult, record_take
from rig.sim.subject import with_sim_subject

from ..bars import Bars


@contextlib.contextmanager
def stop_on_signals(stop: StopFlag) -> Iterator[None]:
    """Ctrl-C and SIGTERM end the take in order (every file finished) instead of killing it."""
    names = {signal.SIGINT: "SIGINT (Ctrl-C)", signal.SIGTERM: "SIGTERM"}

    def handler(signum, _frame) -> None:
        if stop.requested:
            # os.write, not click.echo: a handler must not re-enter a buffered stream
            os.write(2, b"\nstopping: finishing the files of the take...\n")
        stop.signal(f"stopped by {names[signum]}")

    previous = {s: signal.signal(s, handler) for s in names}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def summarize(result: TakeResult) -> str:
    """One line: status, cameras, frames, drops, size; what was lost (cameras, the LED controller)."""
    cams = result.cameras
    frames = result.frames
    drops = sum(c.seq_gaps for c in cams)
    size = sum(c.bytes for c in cams) / 1e6
    per = frames / len(cams) if cams else 0
    line = (f"take {result.path}: {result.status}, {len(cams)} cameras, {frames} frames "
            f"({per:.0f} per camera), {drops} dropped, {size:.1f} MB")
    if result.reason:
        line += f"; {result.reason}"
    if result.lost:
        line += "; lost: " + ", ".join(f"{c.id} ({c.status}: {c.error})" for c in result.lost)
    if result.leds in ("lost", "failed"):
        line += f"; LEDs {result.leds}: " + "; ".join(result.led_errors)
    return line


@click.command()
@click.option("--rig", "rig_file", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="rig.toml of the cameras and LEDs.")
@click.option("--session", "session_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Session folder (created if new; session.toml is kept up to date).")
@click.option("--take", required=True, help="Name of the take folder inside the session.")
@click.option("--kind", required=True, type=click.Choice(KINDS), help="What the take shows.")
@click.option("--duration", type=click.FloatRange(min=0, min_open=True), required=True,
              help="Seconds to record (Ctrl-C or SIGTERM stop earlier, keeping every frame).")
@click.option("--force", is_flag=True, help="Record again over an existing take.")
@click.option("--level", type=click.FloatRange(0, 1), default=None,
              help="LED level for the take (default: the [leds] level).")
@click.option("--flash-ms", type=click.IntRange(1, 60000), default=None,
              help="Flash the LEDs this long during the take (optical sync check).")
@click.option("--flash-every", type=click.FloatRange(min=0, min_open=True), default=1.0, show_default=True,
              help="One flash in each window of this many seconds.")
@click.option("--flash-level", type=click.FloatRange(0, 1), default=None,
              help="Level of a flash (default: dark if the LEDs are at 0.5 or more, else full).")
@click.option("--no-leds", is_flag=True, help="Leave the LED controller alone.")
@click.option("--subject", default=None, help="Subject id (stored in session.toml; sets the simulated subject).")
@click.option("--operator", default=None, help="Operator (stored in session.toml).")
@click.option("--object", "obj", default=None,
              help="Object name (stored in session.toml; sets the simulated object: box, mug, sphere).")
def command(rig_file: Path, session_dir: Path, take: str, kind: str, duration: float, force: bool,
            level: float | None, flash_ms: int | None, flash_every: float, flash_level: float | None,
            no_leds: bool, subject: str | None, operator: str | None, obj: str | None) -> None:
    """Record one take: every camera into SESSION/TAKE/cams/CAM.mkv, frames.csv and take.json.

    A live bar shows the frames stored and their rate. A camera that is lost mid-take is
    reported and the others go on. Ctrl-C, SIGTERM, a full disk or a failing writer end the take
    with every frame received so far readable, marked interrupted with the reason.
    Exit code 0: complete; 1: a camera or the LED controller was lost (the frames are kept) or the
    take failed; 2: bad input or not enough disk; 130: stopped by a signal.
    """
    rig = load_rig(rig_file)
    if all(c.backend == "sim" for c in rig.cameras):   # the simulated cube shows who and what
        rig = with_sim_subject(rig, obj=obj, subject=subject)
    stop = StopFlag()
    options = RecordOptions(force=force, subject=subject, operator=operator, obj=obj, use_leds=not no_leds,
                            level=level, flash_ms=flash_ms, flash_every_s=flash_every, flash_level=flash_level)
    with stop_on_signals(stop), Bars(unit="frame") as bars:
        result = record_take(rig, session_dir, take, kind, duration, options, stop=stop, progress=bars)
    click.echo(summarize(result))
    if result.exit_code:
        raise SystemExit(result.exit_code)
