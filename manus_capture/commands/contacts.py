"""`manus-capture contacts`: hand-object contact maps of a take from the Gaussian models."""

from __future__ import annotations

import hashlib
import time
from pathlib import Path

import click
import cv2
import numpy as np

from dataset_tools.calibration.formats import load_cameras
from manus_capture.bars import Bars
from manus_capture.contact_tasks import FRAMES_PER_TASK, ContactStore, contacts_in_tasks
from manus_capture.contacts import POSE_FRAMES, contact_image, write_contacts
from manus_capture.evaluate import render_contacts
from manus_capture.splat.checkpoint import load_checkpoint
from manus_capture.splat.hand import HandGaussians
from manus_core.dataset import read_dataset
from manus_core.errors import EvaluateError
from manus_core.fileio import write_atomic
from manus_core.provenance import provenance_attrs

from .cluster import cluster_options


@click.command("contacts", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("dataset", type=click.Path(path_type=Path, exists=True, dir_okay=False))
@click.option("--take", "key", required=True, metavar="SESSION/TAKE", help="The grasp take's group in DATASET.")
@click.option("--hand", "hand_path", required=True, type=click.Path(path_type=Path, exists=True, dir_okay=False),
              help="MANUS-Hand checkpoint (reconstruct hand).")
@click.option("--object", "object_path", required=True, type=click.Path(path_type=Path, exists=True, dir_okay=False),
              help="Object checkpoint (reconstruct object).")
@click.option("--tau", type=click.FloatRange(0, min_open=True), default=0.004, show_default=True,
              help="Contact distance (m).")
@click.option("--soft", is_flag=True, help="Soft contact 1 - d/tau instead of 0/1.")
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default="auto", show_default=True,
              help="Neighbour search: KD-tree on the CPU or chunked distances on CUDA (auto: CUDA when the "
                   "process running a task has it).")
@click.option("--calib", type=click.Path(path_type=Path), default=None,
              help="With --renders: the cameras to render the contact map into.")
@click.option("--renders", type=click.Path(path_type=Path, file_okay=False), default=None,
              help="Folder for CAM.png: the accumulated contact on the hand at its firmest grip.")
@cluster_options("into ranges of frames")
@click.option("--frames-per-task", type=click.IntRange(1), default=FRAMES_PER_TASK, show_default=True,
              help=f"Frames per task (rounded down to a multiple of {POSE_FRAMES}, at least {POSE_FRAMES}).")
def command(dataset: Path, key: str, hand_path: Path, object_path: Path, tau: float, soft: bool,
            device: str, calib: Path | None, renders: Path | None, workers: int, scheduler: str | None,
            frames_per_task: int) -> None:
    """Contacts of the hand of take KEY with the object: for every frame, each hand Gaussian's
    nearest object Gaussian (and the reverse), contact below --tau; instantaneous maps (T,G) and
    the accumulated map (G,) into DATASET under KEY/contacts (docs/contacts.md)."""
    if (calib is None) != (renders is None):
        raise click.UsageError("--renders and --calib go together")
    start = time.perf_counter()
    data = read_dataset(dataset)
    if key not in data:
        raise EvaluateError(f"{dataset}: no take {key!r} (takes: {', '.join(data.takes) or 'none'})")
    ann = data[key]   # DatasetError, one line naming the take, when it has no annotation
    angles, source = data.pose_angles(key)
    click.echo(f"contacts: {key}: poses from {source}", err=True)
    annotation = data.provenance(key, "annotate")
    # the recording the poses came from: a later re-recording of the take makes these contacts stale
    inputs = {"take": None if annotation is None else annotation.get("take"),
              "hand_model_sha256": _sha256(hand_path), "object_model_sha256": _sha256(object_path),
              "tau_m": tau, "soft": soft, "angles": source}
    gaussians, extra, meta = load_checkpoint(hand_path)
    if meta.get("kind") != "hand":
        raise EvaluateError(f"{hand_path}: a {meta.get('kind')!r} checkpoint, not a hand")
    hand = HandGaussians.from_checkpoint(gaussians, extra)
    obj, _, meta = load_checkpoint(object_path)
    if meta.get("kind") != "object":
        raise EvaluateError(f"{object_path}: a {meta.get('kind')!r} checkpoint, not an object")
    # the maps go into a file beside the dataset as the tasks finish: a long take's do not fit in memory
    store = ContactStore(len(angles), len(hand), len(obj), dataset.with_name(f".{dataset.name}.{key.replace('/', '-')}"
                                                                              ".contacts.h5"))
    try:
        with Bars(unit="frame") as bars:
            maps = contacts_in_tasks(key, hand_path, object_path, angles, tau, soft, device, workers, scheduler,
                                     frames_per_task, bars, store)
        write_contacts(dataset, key, maps, {"contact_hand_model": str(hand_path),
                                            "contact_object_model": str(object_path),
                                            **provenance_attrs("contacts", inputs)})
        accumulated, object_accumulated = maps.accumulated, maps.object_accumulated
    finally:
        store.close()
    if renders is not None:
        rig = load_cameras(calib)
        hold = int(np.argmax(store.totals))   # the firmest grip: the most hand in contact
        uncalibrated = [c for c in ann.cameras if c not in rig.ids]
        if uncalibrated:
            click.echo(f"note: cameras {', '.join(uncalibrated)} of {key} are not in {calib}: not rendered", err=True)
        with Bars(unit="view") as bars:
            bars("render", 0, len(rig))
            for i in range(len(rig)):
                value, alpha = render_contacts(hand, angles[hold], accumulated, rig.subset([rig.ids[i]]))
                image = contact_image(value[0], alpha[0])
                write_atomic(renders / f"{rig.ids[i]}.png", cv2.imencode(".png", image)[1].tobytes())
                bars("render", i + 1, len(rig))
    touched = int((accumulated > 0.5).sum())
    click.echo(f"contacts: {key}: {len(angles)} frames, {touched}/{len(hand)} hand Gaussians and "
               f"{int((object_accumulated > 0.5).sum())}/{len(obj)} object Gaussians in contact "
               f"(tau {tau * 1000:g} mm) -> {dataset} ({time.perf_counter() - start:.1f} s)")


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()
