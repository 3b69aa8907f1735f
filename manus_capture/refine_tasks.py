"""Pose refinement as tasks (dataset_tools.tasks.run_tasks): one take a task, in this process, in
local processes or on a Dask worker.

A task carries the paths it reads (the dataset, the take), the calibration, the hand model and the
options, and refines on a fixed number of torch threads (torch_threads.py), so that its angles are
the same wherever it ran. Its result comes back to the caller, which alone writes DATASET.h5.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from dataset_tools.tasks import run_tasks
from manus_core.cameras import CameraRig
from manus_core.progress import Progress, silent

from .refine import RefineOptions, RefineResult, refine_take
from .splat.hand import HandGaussians
from .torch_threads import torch_threads


@dataclass(frozen=True)
class RefineTask:
    """The refinement of take `key` of `dataset`, recorded in `take` (picklable, but for
    `progress`: see refine_in_tasks)."""

    dataset: str
    key: str
    take: str
    rig: CameraRig
    model: HandGaussians
    model_path: str
    options: RefineOptions
    threads: int
    progress: Progress = silent


def refine_task(task: RefineTask) -> RefineResult:
    """The refined angles of one task's take."""
    with torch_threads(task.threads):
        return refine_take(Path(task.dataset), task.key, Path(task.take), task.rig, task.model, task.options,
                           task.model_path, task.progress)


def refine_in_tasks(tasks: Sequence[RefineTask], workers: int = 1, scheduler: str | None = None,
                    progress: Progress = silent) -> Iterator[tuple[RefineTask, RefineResult]]:
    """(task, result) as the tasks finish; the first failed task's error is raised. Steps are
    reported to `progress` only when the tasks run in this process: a progress bar does not travel
    to another."""
    here = workers == 1 and scheduler is None
    tasks = [replace(t, progress=progress if here else silent) for t in tasks]
    for task, out in run_tasks(refine_task, tasks, workers, scheduler, key=lambda t: f"refine-{t.key}"):
        if isinstance(out, Exception):
            raise out
        yield task, out
