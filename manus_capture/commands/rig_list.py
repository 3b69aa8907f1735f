"""`manus-capture rig list`: the cameras and serial ports this machine can see."""

from __future__ import annotations

import json

import click

from rig.discovery import discover


@click.command("list")
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of a table.")
@click.option("--no-aravis", is_flag=True, help="Skip GigE/USB3 Vision discovery (about a second).")
@click.option("--fake", is_flag=True, help="Also list Aravis's built-in fake camera (Fake_1).")
def list_command(as_json: bool, no_aravis: bool, fake: bool) -> None:
    """List cameras (V4L2 by-id, Aravis) and serial ports; `device` is what rig.toml takes."""
    found = discover(skip={"aravis"} if no_aravis else (), fake=fake)
    if as_json:
        click.echo(json.dumps(found.to_dict(), indent=2))
    else:
        click.echo(f"cameras ({len(found.cameras)}):")
        for cam in found.cameras:
            details = ", ".join(f"{k} {v}" for k, v in (("model", cam.model), ("serial", cam.serial),
                                                        ("address", cam.address), ("protocol", cam.protocol)) if v)
            click.echo(f"  {cam.backend:7s} {cam.device}  ({details})")
        click.echo(f"serial ports ({len(found.ports)}):")
        for port in found.ports:
            extra = f"  [{port.guess}]" if port.guess else ""
            click.echo(f"  {port.device}  {port.description} {port.hwid}{extra}")
        for note in found.notes:
            click.echo(f"note: {note}")
    n_cam, n_port = len(found.cameras), len(found.ports)
    click.echo(f"found {n_cam} camera{'s' * (n_cam != 1)} and {n_port} serial port{'s' * (n_port != 1)}",
               err=as_json)
