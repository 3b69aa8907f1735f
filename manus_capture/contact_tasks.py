"""A take's contact maps split into ranges of frames, run inline, in local processes or on a Dask
cluster (dataset_tools.tasks.run_tasks), and put back together in frame order.

A frame's instantaneous maps depend on that frame alone (its posed hand against the object), and
the accumulated maps are their maximum over the frames, so the maps of the ranges, stacked, are
those of the whole take, bit for bit on the CPU: ranges start on whole calls of
contacts.POSE_FRAMES, which makes a frame's posed points the same in any range, and the KD-tree
gives each pair's distance from the two points alone. (The CUDA search computes distances in
blocks of CHUNK points, which another split fills differently; that is not checked.)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dataset_tools.tasks import run_tasks
from manus_core.progress import Progress, silent

from .contacts import POSE_FRAMES, ContactMaps, accumulate, model_contacts
from .splat.checkpoint import load_checkpoint
from .splat.hand import HandGaussians

FRAMES_PER_TASK = 512


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
                      frames_per_task: int = FRAMES_PER_TASK, progress: Progress = silent) -> ContactMaps:
    """Contact maps of take `take`: the hand checkpoint `hand` posed by `angles` (T,26) against
    the object checkpoint `obj`, `frames_per_task` frames a task (rounded to whole POSE_FRAMES);
    the first failed task's error is raised."""
    span = max(1, frames_per_task // POSE_FRAMES) * POSE_FRAMES
    hand_path, object_path = str(Path(hand).resolve()), str(Path(obj).resolve())
    # one task even for a take without frames, for the maps' shapes
    tasks = [ContactTask(take, hand_path, object_path, angles[start:start + span], start, tau, soft, device)
             for start in range(0, max(len(angles), 1), span)]
    parts: dict[int, ContactMaps] = {}
    done = 0
    progress("contacts", done, len(angles))
    for task, out in run_tasks(contacts_range, tasks, workers, scheduler, key=_task_key):
        if isinstance(out, Exception):
            raise out
        parts[task.start] = out
        done += len(task.angles)
        progress("contacts", done, len(angles))
    ordered = [parts[start] for start in sorted(parts)]
    return accumulate(np.concatenate([p.instant for p in ordered]),
                      np.concatenate([p.object_instant for p in ordered]), tau, soft)


def _task_key(task: ContactTask) -> str:
    return f"{task.take}-{Path(task.hand).stem}-{task.start}"
