"""Training one Gaussian model as a task (dataset_tools.tasks.run_tasks): reconstruct's object or
hand model, in this process, in a local process or on a Dask worker.

The task carries everything the trainer reads (the views, already read from the takes and cut
to their masks; the initial model; the settings, seed included) and trains on a fixed number of
torch threads (torch_threads.py): the checkpoint is the same wherever the task ran.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from dataset_tools.tasks import run_tasks
from manus_core.progress import Progress, silent

from .splat.gaussians import Gaussians
from .splat.hand import HandConfig, HandGaussians, train_hand
from .splat.trainer import ObjectConfig, Views, train_object
from .torch_threads import torch_threads


@dataclass(frozen=True)
class ObjectTraining:
    """The object model from `views` (picklable, but for `progress`: see train_in_task)."""

    views: Views
    config: ObjectConfig
    threads: int
    progress: Progress = silent

    def train(self) -> Gaussians:
        return train_object(self.views, self.config, progress=self.progress).gaussians


@dataclass(frozen=True)
class HandTraining:
    """MANUS-Hand `model` trained on poses `angles` (P,26) and their views (picklable, but for
    `progress`: see train_in_task)."""

    model: HandGaussians
    angles: torch.Tensor
    views: list[Views]
    config: HandConfig
    threads: int
    progress: Progress = silent

    def train(self) -> HandGaussians:
        train_hand(self.model, self.angles, self.views, self.config, progress=self.progress)
        return self.model


def train_task(task: ObjectTraining | HandTraining) -> Gaussians | HandGaussians:
    """The trained model of a training task."""
    with torch_threads(task.threads):
        return task.train()


def train_in_task(task: ObjectTraining | HandTraining, name: str, workers: int = 1, scheduler: str | None = None,
                  progress: Progress = silent) -> Gaussians | HandGaussians:
    """Run one training task through run_tasks (named `name` on the cluster) and return its model,
    or raise its error. The trainer's steps are reported to `progress` only when the task runs in
    this process: a progress bar does not travel to another."""
    here = workers == 1 and scheduler is None
    task = replace(task, progress=progress if here else silent)
    [(_, out)] = run_tasks(train_task, [task], workers, scheduler, key=lambda _: name)
    if isinstance(out, Exception):
        raise out
    return out
