"""evaluate's scores as tasks (dataset_tools.tasks.run_tasks), inline, in local processes or on a
Dask cluster: the Gaussian hand, the capsule baseline, and one task per camera count of the
ablation (both models trained on that many cameras, then scored). Each task runs on a fixed
number of torch threads (torch_threads.py), so its figures do not depend on where it ran.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from dataset_tools.tasks import run_tasks
from manus_core.cameras import CameraRig

from .builder import ModelInputs
from .contacts import PosedModel, model_contacts
from .evaluate import Scores, score_contacts, spread_cameras
from .splat.checkpoint import load_checkpoint
from .splat.gaussians import Gaussians
from .splat.hand import HandGaussians
from .template import capsule_template
from .torch_threads import torch_threads


@dataclass(frozen=True)
class Scoring:
    """What every score of a grasp needs: its joint angles (T,26), the canonical pose (26,), the
    cameras and paint masks (C,H,W) of the canonical take, the ground-truth views (indices)."""

    angles: np.ndarray
    canonical: np.ndarray
    rig: CameraRig
    paint: np.ndarray
    views: np.ndarray
    tau: float
    threshold: float

    def score(self, hand: PosedModel, obj: Gaussians) -> Scores:
        maps = model_contacts(hand, self.angles, obj, self.tau)
        return score_contacts(hand, self.canonical, maps.accumulated, self.rig, self.paint, self.views,
                              self.threshold)[0]


@dataclass(frozen=True)
class Checkpoints:
    """The object of a checkpoint and MANUS-Hand of another, or instead the capsule template of
    `template_bones` (the baseline)."""

    object: str
    hand: str | None = None
    template_bones: np.ndarray | None = None

    def models(self) -> tuple[PosedModel, Gaussians]:
        obj = load_checkpoint(self.object)[0]
        if self.template_bones is not None:
            return capsule_template(self.template_bones), obj
        gaussians, extra, _ = load_checkpoint(self.hand)
        return HandGaussians.from_checkpoint(gaussians, extra), obj


@dataclass(frozen=True)
class Ablation:
    """Both models trained on `cameras` cameras spread over the rig of `inputs`."""

    inputs: ModelInputs
    cameras: int

    def models(self) -> tuple[PosedModel, Gaussians]:
        trained = self.inputs.train(spread_cameras(self.inputs.rig, self.cameras))
        return trained.hand, trained.object


@dataclass(frozen=True)
class ScoreTask:
    """One score, named `name` ("gaussian", "baseline" or a camera count), for a worker (picklable)."""

    name: str
    models: Checkpoints | Ablation
    scoring: Scoring
    threads: int


def score_task(task: ScoreTask) -> Scores:
    """The Scores of a ScoreTask's models."""
    with torch_threads(task.threads):
        return task.scoring.score(*task.models.models())


def scores_in_tasks(grasp: str, tasks: list[ScoreTask], workers: int = 1,
                    scheduler: str | None = None) -> Iterator[tuple[ScoreTask, Scores]]:
    """(task, its Scores) as the tasks of grasp take `grasp` finish; the first failed task's error
    is raised."""
    for task, out in run_tasks(score_task, tasks, workers, scheduler, key=lambda t: f"{grasp}-{t.name}"):
        if isinstance(out, Exception):
            raise out
        yield task, out
