"""`manus-capture record`: one take from every camera of the rig (docs/recording.md)."""

from __future__ import annotations

import contextlib
import os
import signal
from collections.abc import Callable, Iterator
from pathlib import Path

import click

from dataset_tools.sync import sync_take
from manus_core.errors import ManusError
from manus_core.rig_config import load_rig
from manus_core.session import TAKE_KINDS as KINDS
from rig.record import LiveSession, RecordOptions, StopFlag, TakeResult, record_take
from rig.sim.subject import with_sim_subject

from ..bars import Bars
from ..monitor import parse_address, start_monitor
from .sync_report import echo_report


def monitor_options(fn: Callable) -> Callable:
    """--monitor, --monitor-token and --no-sync-check, shared by record and protocol."""
    fn = click.option("--no-sync-check", is_flag=True,
                      help="Skip the sync validation after each take (sync_report.json; see sync-report).")(fn)
    fn = click.option("--monitor-token", default=None, metavar="TOKEN",
                      help="Token every monitor request must carry (beyond loopback, one is made and "
                           "printed when not given).")(fn)
    return click.option("--monitor", default=None, metavar="[HOST:]PORT",
                        help="Serve a live web page of the recording on [HOST:]PORT (host default 127.0.0.1, "
                             "port 0: any free one); docs/recording.md, \"The monitor\".")(fn)


@contextlib.contextmanager
def monitoring(source: LiveSession, address: str | None, token: str | None) -> Iterator[None]:
    """Serve `source` on `address` ([HOST:]PORT; None: no monitor) while the block runs.

    Started before any camera opens, so that a port in use fails first; its failing to stop
    cannot change what the recording reports.
    """
    if address is None:
        yield
        return
    server = start_monitor(source, *parse_address(address), token)
    click.echo(f"monitor: {server.url}")
    try:
        yield
    finally:
        try:
            server.stop()
        except Exception as exc:   # the takes are on disk: the monitor's end is only worth a note
            click.echo(f"monitor: did not stop cleanly: {type(exc).__name__}: {exc}", err=True)


def check_sync(take_dir: Path) -> str | None:
    """The sync validation of a finished take (sync_report.json/.md written into it) and its
    verdict line: pass, fail, error (it could not run); None when the take left no files."""
    if not (take_dir / "take.json").is_file():
        return None
    try:
        with Bars(unit="camera") as bars:
            report = sync_take(take_dir, force=True, progress=bars)
    except (ManusError, OSError) as exc:   # the frames are recorded; only their check is missing
        click.echo(f"sync check: {take_dir.name}: error: {exc}", err=True)
        return "error"
    echo_report(report, take_dir, "sync check")
    return report["verdict"]


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
@monitor_options
def command(rig_file: Path, session_dir: Path, take: str, kind: str, duration: float, force: bool,
            level: float | None, flash_ms: int | None, flash_every: float, flash_level: float | None,
            no_leds: bool, subject: str | None, operator: str | None, obj: str | None,
            monitor: str | None, monitor_token: str | None, no_sync_check: bool) -> None:
    """Record one take: every camera into SESSION/TAKE/cams/CAM.mkv, frames.csv and take.json.

    A live bar shows the frames stored and their rate (--monitor: a web page too). A camera
    that is lost mid-take is reported and the others go on. Ctrl-C, SIGTERM, a full disk or a
    failing writer end the take with every frame received so far readable, marked interrupted
    with the reason. Then the sync validation writes SESSION/TAKE/sync_report.json/.md and
    prints its verdict (--no-sync-check skips it).
    Exit code 0: complete and the sync check passed; 1: a camera or the LED controller was lost
    (the frames are kept), the take failed, or the sync check did not pass; 2: bad input, not
    enough disk or a monitor port in use; 130: stopped by a signal.
    """
    rig = load_rig(rig_file)
    if all(c.backend == "sim" for c in rig.cameras):   # the simulated cube shows who and what
        rig = with_sim_subject(rig, obj=obj, subject=subject)
    stop = StopFlag()
    options = RecordOptions(force=force, subject=subject, operator=operator, obj=obj, use_leds=not no_leds,
                            level=level, flash_ms=flash_ms, flash_every_s=flash_every, flash_level=flash_level)
    source = LiveSession(rig, session_dir)
    with monitoring(source, monitor, monitor_token):
        with stop_on_signals(stop), Bars(unit="frame") as bars:
            result = record_take(rig, session_dir, take, kind, duration, options, stop=stop, progress=bars,
                                 on_live=source.attach)
        click.echo(summarize(result))
        verdict = None if no_sync_check else check_sync(result.path)
        source.finished(take, verdict, int(result.status == "complete"))
    code = result.exit_code or int(verdict not in (None, "pass"))
    if code:
        raise SystemExit(code)
