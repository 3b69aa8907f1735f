"""A take's contact maps split into ranges of frames, run inline, in local processes or on a Dask
cluster (dataset_tools.tasks.run_tasks), and put back together in frame order.

A frame's instantaneous maps depend on that frame alone (its posed hand against the object), and
the accumulated maps are their maximum over the frames, so the maps of the ranges, stacked, are
those of the whole take, bit for bit on the CPU: ranges start on whole calls of
contacts.POSE_FRAMES, which makes a frame's posed points the same in any range, and the KD-tree
gives each pair's distance from the two points alone. (The CUDA search computes distances in
blocks of CHUNK points, which another split fills differently; that is not checked.)

The ranges' instantaneous maps go into a ContactStore as they finish: numpy arrays, or an HDF5
file beside DATASET.h5, so that a long take needs the memory of a few ranges rather than of the
take (a 10-minute take at 120 FPS is 72,000 frames of 5,000 hand and 4,000 object values).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dataset_tools.tasks import run_tasks
from manus_core.progress import Progress, silent
from manus_core.scratch import ScratchArrays

from .contacts import POSE_FRAMES, ContactMaps, model_contacts
from .splat.checkpoint import load_checkpoint
from .splat.hand import HandGaussians

# A task holds its range's posed points, neighbour search and maps: with 512 frames a 10 s take's
# peak memory was 1.37x a 2 s take's (a range filling up), with 128 frames 1.05x (bench_stages).
FRAMES_PER_TASK = 128
INSTANT, OBJECT_INSTANT = "contacts/instant", "contacts/object_instant"


class ContactStore(ScratchArrays):
    """A take's instantaneous maps (T,G) and (T,M), float16 as DATASET.h5 keeps them, filled range
    by range, and their maxima over the frames so far. `path`: an HDF5 file (created, replaced if
    there), compressed in chunks of POSE_FRAMES frames; None: numpy arrays."""

    def __init__(self, frames: int, hand: int, obj: int, path: Path | None = None) -> None:
        super().__init__(path)
        self.accumulated, self.object_accumulated = np.zeros(hand, np.float32), np.zeros(obj, np.float32)
        self.totals = np.zeros(frames, np.float32)   # each frame's hand contact, summed over the Gaussians
        rows = max(1, min(frames, POSE_FRAMES))
        self.instant, self.object_instant = (self.array(name, (frames, n), np.float16, (rows, max(n, 1)))
                                             for name, n in ((INSTANT, hand), (OBJECT_INSTANT, obj)))

    def put(self, start: int, maps: ContactMaps) -> None:
        """The maps of frames start ... start + n - 1."""
        n = len(maps.instant)
        self.instant[start:start + n] = maps.instant.astype(np.float16)
        self.object_instant[start:start + n] = maps.object_instant.astype(np.float16)
        np.maximum(self.accumulated, maps.accumulated, out=self.accumulated)
        np.maximum(self.object_accumulated, maps.object_accumulated, out=self.object_accumulated)
        self.totals[start:start + n] = maps.instant.sum(axis=1)

    def maps(self, tau: float, soft: bool) -> ContactMaps:
        """The take's maps; the instantaneous ones stay in the store (arrays or HDF5 datasets)."""
        return ContactMaps(self.instant, self.accumulated, self.object_instant, self.object_accumulated, tau, soft)


@dataclass(frozen=True)
class ContactTask:
    """Frames [start, start + len(angles)) of take `take` (its key in the dataset), for a worker
    (picklable): the two models travel as their checkpoints' paths."""

    take: str
    hand: str
    object: str
    angles: np.ndarray    # (n,26) of these frames
    start: int
    tau: float
    soft: bool
    device: str           # auto, cpu or cuda: auto is decided where the task runs


def contacts_range(task: ContactTask) -> ContactMaps:
    """The contact maps of a ContactTask's frames."""
    gaussians, extra, _ = load_checkpoint(task.hand)
    obj, _, _ = load_checkpoint(task.object)
    device = task.device
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    return model_contacts(HandGaussians.from_checkpoint(gaussians, extra), task.angles, obj, task.tau, task.soft,
                          device)


def contacts_in_tasks(take: str, hand: Path, obj: Path, angles: np.ndarray, tau: float, soft: bool,
                      device: str = "cpu", workers: int = 1, scheduler: str | None = None,
                      frames_per_task: int = FRAMES_PER_TASK, progress: Progress = silent,
                      store: ContactStore | None = None) -> ContactMaps:
    """Contact maps of take `take`: the hand checkpoint `hand` posed by `angles` (T,26) against
    the object checkpoint `obj`, `frames_per_task` frames a task (rounded to whole POSE_FRAMES),
    each task's maps into `store` as it finishes (default: arrays in memory); the first failed
    task's error is raised."""
    span = max(1, frames_per_task // POSE_FRAMES) * POSE_FRAMES
    hand_path, object_path = str(Path(hand).resolve()), str(Path(obj).resolve())
    # one task even for a take without frames, for the maps' shapes
    tasks = [ContactTask(take, hand_path, object_path, angles[start:start + span], start, tau, soft, device)
             for start in range(0, max(len(angles), 1), span)]
    done = 0
    progress("contacts", done, len(angles))
    for task, out in run_tasks(contacts_range, tasks, workers, scheduler, key=_task_key):
        if isinstance(out, Exception):
            raise out
        if store is None:
            store = ContactStore(len(angles), out.instant.shape[1], out.object_instant.shape[1])
        store.put(task.start, out)
        done += len(task.angles)
        progress("contacts", done, len(angles))
    return store.maps(tau, soft)


def _task_key(task: ContactTask) -> str:
    return f"{task.take}-{Path(task.hand).stem}-{task.start}"
