"""`manus-capture leds on|off|set LEVEL|flash MS|status --rig rig.toml`."""

from __future__ import annotations

import time
from pathlib import Path

import click

from manus_core.errors import NoLedsError
from manus_core.rig_config import LedConfig, load_rig
from rig.leds import LedController, open_led_controller

rig_option = click.option("--rig", "rig_file", required=True,
                          type=click.Path(dir_okay=False, path_type=Path),
                          help="rig.toml whose [leds] table names the controller.")


def _open(rig_file: Path) -> tuple[LedConfig, LedController]:
    rig = load_rig(rig_file)
    if rig.leds is None:
        raise NoLedsError(f"{rig_file}: leds: missing (add a [leds] table with port and protocol)")
    return rig.leds, open_led_controller(rig.leds)


def _where(cfg: LedConfig, record: dict) -> str:
    ack = record.get("t_ack_ns") or record.get("t_done_ns")
    latency = f" after {(ack - record['t_send_ns']) / 1e6:.1f} ms" if ack else ""
    return f"({cfg.protocol} on {cfg.port}{latency})"


@click.group()
def command() -> None:
    """Switch, set and flash the LED panels of the rig's controller."""


@command.command("on")
@rig_option
@click.option("--level", type=click.FloatRange(0, 1), default=None,
              help="Level 0..1 (default: the [leds] level).")
def on(rig_file: Path, level: float | None) -> None:
    """All panels on."""
    cfg, leds = _open(rig_file)
    with leds:
        record = leds.on(level)
        click.echo(f"leds: {leds.panels} panels at {leds.levels[0]:.2f} {_where(cfg, record)}")


@command.command("off")
@rig_option
def off(rig_file: Path) -> None:
    """All panels off."""
    cfg, leds = _open(rig_file)
    with leds:
        record = leds.off()
        click.echo(f"leds: {leds.panels} panels off {_where(cfg, record)}")


@command.command("set")
@click.argument("level", type=click.FloatRange(0, 1))
@rig_option
@click.option("--panel", type=click.IntRange(min=0), default=None, help="Only this panel (0-based).")
def set_level(level: float, rig_file: Path, panel: int | None) -> None:
    """Set LEVEL (0..1) on every panel, or on one with --panel."""
    cfg, leds = _open(rig_file)
    with leds:
        if panel is None:
            record = leds.set_levels([level] * leds.panels)
            what = f"{leds.panels} panels"
        else:
            record = leds.set_panel(panel, level)
            what = f"panel {panel}"
        click.echo(f"leds: {what} at {level:.2f} {_where(cfg, record)}")


@command.command("flash")
@click.argument("ms", type=click.IntRange(1, 60000))
@rig_option
@click.option("--level", type=click.FloatRange(0, 1), default=1.0, show_default=True)
def flash(ms: int, rig_file: Path, level: float) -> None:
    """Flash every panel for MS milliseconds, then return to the previous levels."""
    cfg, leds = _open(rig_file)
    with leds:
        record = leds.flash(ms, level)
        # A host-timed (DMX) flash ends only if the process is still there to end it.
        time.sleep(ms / 1000 + 0.01)
        click.echo(f"leds: flashed {leds.panels} panels for {ms} ms at {level:.2f} {_where(cfg, record)}")


@command.command("status")
@rig_option
def status(rig_file: Path) -> None:
    """Ask the controller for its state."""
    cfg, leds = _open(rig_file)
    with leds:
        state = leds.status()
        levels = " ".join(f"{x:.2f}" for x in state.get("levels", []))
        details = ", ".join(f"{k} {v}" for k, v in state.items() if k != "levels")
        click.echo(f"leds: {cfg.protocol} on {cfg.port}: levels {levels}; {details}")
