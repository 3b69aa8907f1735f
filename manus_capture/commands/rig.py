"""`manus-capture rig`: create, check and list rig configurations."""

from __future__ import annotations

import re
from collections import Counter
from pathlib import Path

import click

from manus_core.fileio import write_atomic
from manus_core.rig_config import BACKENDS, PLACEHOLDER, SYNC_MODES, load_rig, rig_to_toml
from rig.layouts import LAYOUTS, make_rig

from .rig_list import list_command


def _resolution(ctx, param, value: str) -> tuple[int, int]:
    m = re.fullmatch(r"(\d+)x(\d+)", value)
    if not m or int(m[1]) < 16 or int(m[2]) < 16:
        raise click.BadParameter(f"{value!r} is not WIDTHxHEIGHT (e.g. 1280x720)")
    return int(m[1]), int(m[2])


@click.group()
def command() -> None:
    """Create (init), validate (check) and discover (list) rig configurations."""


@command.command("init")
@click.option("--layout", type=click.Choice(sorted(LAYOUTS)), default="cube53", show_default=True,
              help="Camera layout.")
@click.option("--cameras", type=click.IntRange(min=1), default=None,
              help="Keep N cameras spread over all faces of the layout (default: all).")
@click.option("--resolution", default="1280x720", show_default=True, callback=_resolution,
              help="Camera resolution WIDTHxHEIGHT.")
@click.option("--fps", type=click.FloatRange(min=1), default=120.0, show_default=True)
@click.option("--backend", type=click.Choice(BACKENDS), default="sim", show_default=True)
@click.option("--sync", type=click.Choice(SYNC_MODES), default="free-run", show_default=True)
@click.option("--seed", type=int, default=0, show_default=True,
              help="Seed of the simulated imperfections (clock offsets, drift, phases, drops).")
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="rig.toml to write.")
@click.option("--force", is_flag=True, help="Overwrite an existing file.")
def init(layout, cameras, resolution, fps, backend, sync, seed, output: Path, force: bool) -> None:
    """Write a rig.toml for a layout, with every camera and every simulated imperfection spelled out."""
    if output.exists() and not force:
        raise click.UsageError(f"{output} exists; use --force to overwrite it")
    rig = make_rig(layout, cameras, resolution, fps, backend, seed, sync)
    write_atomic(output, rig_to_toml(rig).encode())
    click.echo(f"wrote {output}: {len(rig.cameras)} {backend} cameras, {resolution[0]}x{resolution[1]} "
               f"at {fps:g} FPS, {sync}")
    if backend != "sim":
        click.echo(f"  each camera's device is {PLACEHOLDER}: put in its serial number or /dev/v4l/by-id path "
                   "(`manus-capture rig list` shows them); `rig check` and `record` refuse the file until then")


@command.command("check")
@click.argument("rig_file", type=click.Path(dir_okay=False, path_type=Path))
def check(rig_file: Path) -> None:
    """Validate RIG_FILE and print a summary; exit 2 with one line naming the key if it is wrong."""
    rig = load_rig(rig_file)
    backends = Counter(c.backend for c in rig.cameras)
    sizes = Counter(f"{c.width}x{c.height}@{c.fps:g}" for c in rig.cameras)
    click.echo(f"{rig_file}: rig '{rig.name}' ({rig.layout}), {len(rig.cameras)} cameras")
    click.echo("  backends:   " + ", ".join(f"{n} {b}" for b, n in sorted(backends.items())))
    click.echo("  modes:      " + ", ".join(f"{n} x {s}" for s, n in sorted(sizes.items())))
    click.echo(f"  sync:       {rig.sync} at {rig.fps:g} FPS")
    if rig.leds is None:
        click.echo("  LEDs:       none")
    else:
        click.echo(f"  LEDs:       {rig.leds.protocol} on {rig.leds.port}, {rig.leds.panels} panels")
    if rig.sim is not None:
        s = rig.sim
        click.echo(f"  simulation: cube {s.cube_edge} m, subject {s.subject}, object {s.object}"
                   f"{' (painted)' if s.paint else ''}, time scale {s.time_scale:g}")
    click.echo("ok")


command.add_command(list_command)
