"""Masks of a take's frame groups, the part of segmentation that is split into tasks (a range of
groups each) and run inline, in local processes or on a Dask cluster (dataset_tools.tasks)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from manus_core.cameras import CameraRig
from manus_core.errors import SegmentationError
from manus_core.progress import Progress, silent
from manus_core.take import Take

from ..tasks import run_tasks
from .background import BackgroundModel
from .colour import ColourModel
from .store import MaskStore, ViewMasks
from .views import hand_object_masks

GROUPS_PER_TASK = 64
TASK_MASK_BYTES = 64 << 20   # a task's result at most: fewer groups a task for many cameras or large images

# (background take, cameras) -> its background models and warnings: fitted once per process, and
# only the last kept (53 cameras at 1280x720 are ~0.8 GB)
_BACKGROUNDS: dict[tuple[str, tuple[str, ...]], tuple[list[BackgroundModel | None], list[str]]] = {}


def sample_frames(take: Take, cam: str, count: int = 5) -> np.ndarray:
    """`count` frames (N,H,W,3) spread evenly over one camera of a take."""
    n = take.frame_count(cam)
    if n == 0:
        raise SegmentationError(f"{take.path}: camera {cam} has no frames")
    return np.stack([image for _, image in take.stream_frames(cam, np.linspace(0, n - 1, count).astype(int))])


def backgrounds_for(take: Take, cameras: Sequence[str], background: Take, report: dict) -> list[BackgroundModel | None]:
    """One background per camera `cameras` of `take`; a camera missing from the background take
    gets None and a warning in the report (its masks stay empty). Fitted once per process."""
    key = (str(background.path.resolve()), tuple(cameras))
    if key not in _BACKGROUNDS:
        models, warnings = [], []
        for cam in cameras:
            if cam not in background.cameras or background.frame_count(cam) == 0:
                warnings.append(f"camera {cam}: no frames in background take {background.path}; no masks")
                models.append(None)
            else:
                models.append(BackgroundModel.fit(sample_frames(background, cam)))
        if all(b is None for b in models):
            raise SegmentationError(f"{background.path}: shares no camera with {take.path}")
        _BACKGROUNDS.clear()
        _BACKGROUNDS[key] = models, warnings
    models, warnings = _BACKGROUNDS[key]
    report["warnings"].extend(warnings)
    return list(models)


@dataclass(frozen=True)
class SegmentTask:
    """Frame groups [start, start + len(frame_index)) of a take, for a worker (picklable). The
    backgrounds travel as the background take's path: each process fits them once."""

    take: str
    rig: CameraRig
    background: str
    model: ColourModel | None
    frame_index: np.ndarray      # (n, C): each camera's frame in each of these groups, -1: none
    start: int
    shape: tuple[int, int]


def segment_range(task: SegmentTask) -> list[ViewMasks]:
    """Hand and object masks of a SegmentTask's groups, by view."""
    take = Take(task.take)
    backgrounds = backgrounds_for(take, task.rig.ids, Take(task.background), {"warnings": []})
    return segment_groups(take, task.rig, backgrounds, task.model, task.frame_index, task.shape)


def segment_in_tasks(take: Take, rig: CameraRig, background: Path, model: ColourModel | None,
                     frame_index: np.ndarray, store: MaskStore, workers: int = 1, scheduler: str | None = None,
                     progress: Progress = silent, per_task: int = GROUPS_PER_TASK) -> None:
    """Hand and object masks of the groups frame_index (T,C) into `store` (its shape (T,C,H,W)),
    at most `per_task` groups (and TASK_MASK_BYTES of masks) a task, run through run_tasks; the
    first failed task's error is raised."""
    T, shape = len(frame_index), store.hand.shape[2:]
    per_task = max(1, min(per_task, TASK_MASK_BYTES // (2 * len(rig) * shape[0] * shape[1])))
    tasks = [SegmentTask(str(take.path.resolve()), rig, str(Path(background).resolve()), model,
                         frame_index[start:start + per_task], start, shape)
             for start in range(0, T, per_task)]
    done = 0
    progress("segment", done, T)
    for task, out in run_tasks(segment_range, tasks, workers, scheduler, key=_task_key):
        if isinstance(out, Exception):
            raise out
        store.put_views(task.start, out)
        done += len(task.frame_index)
        progress("segment", done, T)


def _task_key(task: SegmentTask) -> str:
    return f"segment-{Path(task.take).name}-{task.start}"


def segment_groups(take: Take, rig: CameraRig, backgrounds: list, model, frame_index: np.ndarray,
                   shape: tuple[int, int]) -> list[ViewMasks]:
    """Hand and object masks of the frame groups frame_index (T,C), cameras of `rig`: the views that
    show either, each in its window."""
    h, w = shape
    object_take = take.meta.get("kind") == "object"
    out = []
    # one sequential pass over each camera's video: a group's frames come later in every video
    # than the previous group's (reading each frame from the start made the cost grow with the
    # square of the take's length)
    # one buffer for every group, each camera's frames decoded into its view: a view not captured
    # has no background and its pixels are not read
    images = np.zeros((len(rig), h, w, 3), np.uint8)
    streams = [take.stream_frames(cam, frame_index[:, c], out=images[c]) for c, cam in enumerate(rig.ids)]
    current = [-1] * len(rig)
    for t in range(len(frame_index)):
        present = frame_index[t] >= 0
        for c in np.flatnonzero(present):
            while current[c] < frame_index[t, c]:
                current[c] = next(streams[c])[0]
            if current[c] != frame_index[t, c]:
                raise SegmentationError(f"{take.path}: camera {rig.ids[c]}: frame groups out of time order "
                                        f"(frame {frame_index[t, c]} after {current[c]})")
        bgs = [b if p else None for b, p in zip(backgrounds, present)]
        hand, obj, report = hand_object_masks(images, bgs, rig, model)
        if object_take:
            hand, obj = obj, hand
        # copies: a view into the group's masks would keep all of them
        out += [ViewMasks(t, c, window, hand[c][window].copy(), obj[c][window].copy())
                for c, window in enumerate(report["windows"]) if window is not None]
    return out
