"""`manus-capture models`: install and list the hand keypoint models."""

from __future__ import annotations

import click

from dataset_tools.keypoints.install import bundle_dir, install, list_models
from manus_capture.bars import Bars


@click.group("models", context_settings={"help_option_names": ["-h", "--help"]})
def command() -> None:
    """Install and list the hand keypoint models (cached in $XDG_CACHE_HOME/manus-capture/models)."""


@command.command("install")
@click.argument("name")
@click.option("--force", is_flag=True, help="Download, convert and check again even if installed.")
def install_cmd(name: str, force: bool) -> None:
    """Install model NAME (mediapipe-hand: MediaPipe's hand landmark and palm models, as ONNX).

    Downloads the mediapipe==0.10.21 wheel with `pip download --no-deps`, extracts its .tflite
    models, converts them with tflite2onnx in a private environment under the cache directory,
    checks each against the TFLite interpreter on a fixed input, and caches the result. A second
    run does nothing.
    """
    with Bars() as bars:
        changed = install(name, force=force, progress=bars)
    click.echo(f"{name}: installed in {bundle_dir(name)}" if changed
               else f"{name}: already installed in {bundle_dir(name)}; nothing to do")


@command.command("list")
def list_cmd() -> None:
    """List the installable models and whether they are installed."""

    rows = list_models()
    for row in rows:
        state = "installed" if row["installed"] else "not installed"
        click.echo(f"{row['name']:<16} {state:<14} {row['description']}")
        if row["installed"]:
            click.echo(f"{'':<16} {row['path']}: {', '.join(row['files'])}")
    click.echo(f"{sum(r['installed'] for r in rows)} of {len(rows)} models installed; also usable: "
               "mediapipe-hand-lite, or a SimCC/heatmap model spec (.toml)")
