"""`manus-capture monitor SESSION_OR_TAKE`: the monitor page over recorded takes (docs/recording.md)."""

from __future__ import annotations

import time
from pathlib import Path

import click

from manus_capture.monitor import DEFAULT_HOST, DEFAULT_PORT, RecordedSource, start_monitor


@click.command()
@click.argument("path", metavar="SESSION_OR_TAKE", type=click.Path(path_type=Path))
@click.option("--host", default=DEFAULT_HOST, show_default=True,
              help="Address to serve on; anything but loopback needs a token.")
@click.option("--port", type=click.IntRange(0, 65535), default=DEFAULT_PORT, show_default=True,
              help="Port to serve on (0: any free port).")
@click.option("--monitor-token", "token", default=None,
              help="Token every request must carry (?token=); generated and printed for a non-loopback host.")
def command(path: Path, host: str, port: int, token: str | None) -> None:
    """Serve the monitor page for a recorded take or a whole session, until Ctrl-C.

    Per take: each camera's frames by index (a slider), counts, drops and rates, the sync
    verdict and timeline when sync-report has run; for a session, its takes and their verdicts.
    Read-only. Exit code 2: not a take or session folder, or the port is in use.
    """
    source = RecordedSource(path)
    server = start_monitor(source, host, port, token)
    takes = len(source.takes)
    click.echo(f"monitor: {path} ({takes} take{'s' if takes != 1 else ''}) at {server.url} (Ctrl-C to stop)")
    if server.token_generated:
        click.echo(f"monitor: {host} is not loopback: requests need the token {server.token}")
    try:
        while server.running:
            time.sleep(0.5)
    except KeyboardInterrupt:
        server.stop()
        click.echo("monitor: stopped")
        return
    raise click.ClickException(f"monitor: the server stopped ({server.error or 'no reason given'})")
