"""`manus-capture protocol`: the capture protocol of MANUS-Grasps, one take per step.

calibration (empty cube) -> hand articulation routine -> object alone -> grasp x N, each followed
by the canonical pose when the object carries wet paint (the paint on the hand is the contact
ground truth). Takes already complete in session.toml are skipped, so an interrupted session is
resumed by running the same command again. Each take's sync check decides whether it is recorded
again before the subject leaves.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import click

from manus_core.rig_config import load_rig
from manus_core.session import Session, open_session
from rig.leds import LedController, open_led_controller
from rig.record import LiveSession, RecordOptions, StopFlag, record_take
from rig.sim.subject import with_sim_subject

from ..bars import Bars
from .record import check_sync, monitor_options, monitoring, stop_on_signals, summarize

INSTRUCTIONS = {
    "calibration": "Empty cube: nothing inside, LEDs on. The cameras see only the tags on the walls.",
    "hand": "Hand articulation: in the middle of the cube, open and close the hand, spread and join the "
            "fingers, touch each fingertip with the thumb, turn the wrist.",
    "object": "Object alone: put it on the table and leave it; nobody in the cube.",
    "grasp": "Grasp: reach for the object, pick it up, hold it, put it back down and let go.",
    "canonical": "Canonical pose: hand open, fingers spread, palm to the front, still (the paint shows).",
}
DURATION_S = {"calibration": 3.0, "hand": 10.0, "object": 5.0, "grasp": 6.0, "canonical": 3.0}
CUE_FLASHES = 2          # "get ready": two short flashes, then the take starts
CUE_MS = 150
AUTO_RETRIES = 1         # unattended, a take whose sync check did not pass is recorded again this often


@dataclass(frozen=True)
class Step:
    name: str
    kind: str
    duration_s: float
    instruction: str


def protocol_steps(paint: bool, repeats: int, duration_s: float | None = None) -> list[Step]:
    """The takes of one object's session, in order, named NN-kind (grasps and poses numbered)."""
    kinds = [("calibration", ""), ("hand", ""), ("object", "")]
    for i in range(1, repeats + 1):
        kinds.append(("grasp", str(i)))
        if paint:
            kinds.append(("canonical", str(i)))
    return [Step(f"{n:02d}-{kind}{suffix}", kind, duration_s or DURATION_S[kind], INSTRUCTIONS[kind])
            for n, (kind, suffix) in enumerate(kinds)]


def _cue(leds: LedController, level: float) -> None:
    """Tell the person in the cube that a take starts now: CUE_FLASHES short flashes."""
    for _ in range(CUE_FLASHES):
        leds.flash(CUE_MS, 0.0 if level >= 0.5 else 1.0)
        time.sleep(2 * CUE_MS / 1000)
    time.sleep(0.5)


@click.command()
@click.option("--rig", "rig_file", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="rig.toml of the cameras and LEDs.")
@click.option("--session", "session_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Session folder (one subject, one object).")
@click.option("--object", "obj", required=True, help="The object (on the simulated rig: box, mug or sphere).")
@click.option("--paint", is_flag=True, help="Wet green paint on the object: a canonical pose after each grasp.")
@click.option("--repeats", type=click.IntRange(2, 5), default=3, show_default=True, help="Grasps to record.")
@click.option("--duration", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Seconds per take (default per kind: " +
                   ", ".join(f"{k} {v:g}" for k, v in DURATION_S.items()) + ").")
@click.option("--subject", default=None, help="Subject id (default: the simulated subject, or empty).")
@click.option("--operator", default=None, help="Operator (default: the login name).")
@click.option("--flash-ms", type=click.IntRange(1, 60000), default=None,
              help="Flash the LEDs this long in every take (optical sync check).")
@click.option("--no-leds", is_flag=True, help="Leave the LED controller alone (no cues).")
@click.option("--yes", "-y", is_flag=True,
              help="No keyboard: record every step and re-record a failed take once, without asking.")
@monitor_options
def command(rig_file: Path, session_dir: Path, obj: str, paint: bool, repeats: int, duration: float | None,
            subject: str | None, operator: str | None, flash_ms: int | None, no_leds: bool, yes: bool,
            monitor: str | None, monitor_token: str | None, no_sync_check: bool) -> None:
    """Walk through the capture protocol: calibration, hand, object, grasps (and canonical poses).

    Each step prints what the subject does; Enter records it (after an LED cue of two short
    flashes), 's' skips it, 'q' quits. After each take its sync check prints a verdict; one that
    does not pass asks whether to record the take again. --yes answers every question with yes
    (a failed take is recorded again once); on a simulated rig it runs unattended the same way and
    the options set the simulated object and paint. Exit code 0: every take complete and passing
    its sync check; 1: a take failed, lost a camera or did not pass; 2: bad input or a monitor port
    in use; 130: stopped by a signal.
    """
    rig = load_rig(rig_file)
    simulated = all(c.backend == "sim" for c in rig.cameras)
    if simulated:
        rig = with_sim_subject(rig, obj=obj, paint=paint, subject=subject)
    unattended = yes or simulated
    steps = protocol_steps(paint, repeats, duration)
    source = LiveSession(rig, session_dir, total=len(steps))
    with monitoring(source, monitor, monitor_token):
        session = open_session(session_dir, rig, subject=subject, operator=operator, obj=obj, paint=paint)
        leds = None
        if rig.leds is not None and not no_leds:
            leds = open_led_controller(rig.leds)
        options = RecordOptions(force=True, subject=subject, operator=operator, obj=obj,
                                use_leds=leds is not None, flash_ms=flash_ms)
        worst = 0
        try:
            for i, step in enumerate(steps, 1):
                done = session.take(step.name)
                if done is not None and done.get("status") == "complete":
                    click.echo(f"[{i}/{len(steps)}] {step.name}: already complete, skipped")
                    continue
                click.echo(f"[{i}/{len(steps)}] {step.name} ({step.kind}, {step.duration_s:g} s): {step.instruction}")
                if not unattended:
                    answer = click.prompt("Enter: record, s: skip, q: quit", default="",
                                          show_default=False).strip().lower()
                    if answer == "q":
                        break
                    if answer == "s":
                        continue
                retries = 0
                while True:
                    if leds is not None and not simulated:
                        _cue(leds, rig.leds.level)
                    stop = StopFlag()
                    with stop_on_signals(stop), Bars(unit="frame") as bars:
                        result = record_take(rig, session_dir, step.name, step.kind, step.duration_s, options,
                                             leds=leds, stop=stop, progress=bars, on_live=source.attach)
                    session = open_session(session_dir, rig)
                    click.echo("  " + summarize(result))
                    verdict = None if no_sync_check else check_sync(result.path)
                    source.finished(step.name, verdict, _complete(session, steps))
                    passed = verdict in (None, "pass")
                    if result.status == "interrupted" or passed or not _again(step.name, verdict, unattended, retries):
                        break
                    retries += 1
                worst = max(worst, result.exit_code, int(not passed))
                if result.status == "interrupted":
                    break
        finally:
            if leds is not None:
                leds.close()
    complete = _complete(session, steps)
    click.echo(f"session {session_dir}: {complete}/{len(steps)} takes complete "
               f"({session.object or obj}{', painted' if paint else ''}, subject {session.subject or '-'})")
    if worst or complete < len(steps):
        raise SystemExit(worst or 1)


def _complete(session: Session, steps: list[Step]) -> int:
    return sum(1 for s in steps if (session.take(s.name) or {}).get("status") == "complete")


def _again(take: str, verdict: str, unattended: bool, retries: int) -> bool:
    """Whether to record `take` again after a sync check that did not pass."""
    if unattended:
        if retries < AUTO_RETRIES:
            click.echo(f"  {take}: sync check {verdict}: recording it again")
            return True
        click.echo(f"  {take}: sync check {verdict} again: kept as it is, and the session fails")
        return False
    return click.confirm(f"  {take}: sync check {verdict}: record it again?", default=True)
