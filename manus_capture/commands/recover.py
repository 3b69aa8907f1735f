"""`manus-capture recover`: finish a take whose recorder was killed (docs/recording.md)."""

from __future__ import annotations

from pathlib import Path

import click

from rig.record import recover_take


@click.command()
@click.argument("take", type=click.Path(file_okay=False, path_type=Path))
def command(take: Path) -> None:
    """Finish TAKE after its recorder was killed (SIGKILL, a crash): take.json still says "recording".

    Every frame with a frames.csv row is kept as it is; take.json gets the per-camera counts and
    the status "interrupted" with the reason, session.toml is updated and the disk reserve is
    given back. Nothing is re-encoded or moved. Exit code 0: recovered; 2: not a killed take.
    """
    found = recover_take(take)
    line = f"recover {found.path}: interrupted, {found.total} frames kept"
    extra = {c: n for c, n in found.packets_without_row.items() if n}
    if extra:
        line += "; packets without a frames.csv row (not usable, left in the video): " + ", ".join(
            f"{c} {n}" for c, n in extra.items())
    click.echo(line)
    missing = {c: n for c, n in found.rows_without_packet.items() if n}
    if missing:
        click.echo("warning: frames.csv rows without a packet: " + ", ".join(f"{c} {n}" for c, n in missing.items()),
                   err=True)
