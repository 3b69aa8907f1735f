"""Keypoints of every frame of every camera of a take, and the take's keypoints2d.h5.

Frame groups across cameras come later (sync), so keypoints are kept per camera, indexed by the
camera's own frame index (its rows of frames.csv):

    keypoints2d.h5
      attrs: format = "manus-capture keypoints2d", version = 1, model, model_file, box_source,
             joint_names (21, MediaPipe order), take
      cameras/CAM/keypoints   (F_cam,21,3) float32 [x, y, confidence], full-image pixels;
                              NaN and confidence 0 where no hand was looked for or found
      cameras/CAM/boxes       (F_cam,4) float32 the hand box each frame was cropped from (NaN: none)
      cameras/CAM/angles      (F_cam,) float32 the hand-axis angle given with the box (NaN: searched)

Boxes file (`--boxes`): an .npz with one array per camera id, (F_cam,4) x0,y0,x1,y1 or (F_cam,5)
with the hand-axis angle (radians, see boxes.py) in the last column; NaN rows are frames without
a hand. Without it, MediaPipe's palm detector finds the hand: by default in the first frame of
every chunk of frames and wherever the hand is lost, the other frames cropped around the previous
frame's keypoints, as MediaPipe's tracker runs (`track=False`: the palm detector in every frame).
"""

from __future__ import annotations

import io
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from itertools import islice
from pathlib import Path

import h5py
import numpy as np

from manus_core.errors import ModelError, TakeError
from manus_core.fileio import write_atomic
from manus_core.progress import Progress, silent
from manus_core.take import Take

from . import boxes as bx
from .detector import Detector
from .models import JOINT_NAMES, NUM_JOINTS

FORMAT = "manus-capture keypoints2d"


@dataclass
class CameraKeypoints:
    keypoints: np.ndarray   # (F,21,3)
    boxes: np.ndarray       # (F,4)
    angles: np.ndarray      # (F,)


@dataclass
class TakeKeypoints:
    cameras: dict[str, CameraKeypoints]
    model: str
    model_file: str
    box_source: str
    attrs: dict = field(default_factory=dict)


def box_source(boxes: str | Path | None, track: bool) -> str:
    """keypoints2d.h5's `box_source`: file:PATH, palm-detector+tracking or palm-detector."""
    return f"file:{boxes}" if boxes else "palm-detector+tracking" if track else "palm-detector"


def load_boxes(path: str | Path, take: Take, cameras: Sequence[str]) -> dict[str, np.ndarray]:
    """Read a boxes .npz: per camera (F_cam,5) [x0, y0, x1, y1, angle] with NaN angle where absent."""
    path = Path(path)
    try:
        data = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise ModelError(f"{path}: no such boxes file") from None
    except (ValueError, OSError) as exc:
        raise ModelError(f"{path}: not a readable .npz of boxes ({exc})") from None
    out = {}
    with data:
        for cam in cameras:
            if cam not in data.files:
                have = ", ".join(data.files) or "none"
                raise ModelError(f"{path}: no boxes for camera {cam!r} (has {have})")
            b = np.asarray(data[cam], dtype=np.float64)
            frames = take.frame_count(cam)
            if b.ndim != 2 or b.shape[1] not in (4, 5) or len(b) != frames:
                raise ModelError(f"{path}: boxes of camera {cam} have shape {b.shape}, expected "
                                 f"({frames}, 4) or ({frames}, 5) for its {frames} frames")
            if b.shape[1] == 4:
                b = np.concatenate([b, np.full((len(b), 1), np.nan)], axis=1)
            out[cam] = b
    return out


def detect_take(take: Take, detector: Detector, boxes: dict[str, np.ndarray] | None = None,
                cameras: Sequence[str] | None = None, chunk: int = 16, min_score: float = 0.5,
                progress: Progress = silent, track: bool = True) -> dict[str, CameraKeypoints]:
    """Keypoints of every frame of the given cameras (default: all), `chunk` frames per network call.

    boxes: per camera (F,5) as load_boxes gives; None: the palm detector finds one hand, in every
    frame, or with `track` in the first frame of each chunk and where the hand is lost, each other
    frame cropped around the previous one's keypoints (one pass of the keypoint model a frame).
    Reports progress("detect", frames done, frames of all the cameras). Frames past the end of a
    video cut short (Take.missing_frames) stay undetected.
    """
    cameras = list(cameras or take.cameras)
    total = sum(take.readable_frames(cam) for cam in cameras)
    done = [0]

    def batch_done(n: int) -> None:
        done[0] += n
        progress("detect", done[0], total)

    progress("detect", 0, total)
    result = {}
    for cam in cameras:
        kp, used = _empty(take.frame_count(cam))
        _detect_frames(detector, take.iter_frames(cam, 0, take.readable_frames(cam)),
                       None if boxes is None else boxes[cam], chunk, min_score, track, kp, used, batch_done)
        result[cam] = _camera_keypoints(kp, used)
    return result


@dataclass(frozen=True)
class DetectTask:
    """Frames [start, stop) of one camera of a take, for a worker (picklable: a process pool or Dask)."""

    take: str
    camera: str
    start: int
    stop: int
    model: str
    device: str
    chunk: int
    min_score: float
    boxes: np.ndarray | None   # (stop - start, 5) of these frames; None: the palm detector
    track: bool = True         # with the palm detector: track from frame to frame within a chunk


_DETECTORS: dict[tuple[str, str], Detector] = {}


def detect_range(task: DetectTask) -> tuple[np.ndarray, np.ndarray]:
    """(keypoints (n,21,3), boxes and angles used (n,5)) of a DetectTask's frames; the detector is
    loaded once per process."""
    from .detector import hand_keypoint_detector

    if (task.model, task.device) not in _DETECTORS:
        _DETECTORS[task.model, task.device] = hand_keypoint_detector(task.model, device=task.device)
    kp, used = _empty(task.stop - task.start)
    frames = ((k - task.start, image) for k, image in Take(task.take).iter_frames(task.camera, task.start, task.stop))
    _detect_frames(_DETECTORS[task.model, task.device], frames, task.boxes, task.chunk, task.min_score, task.track,
                   kp, used)
    return kp, used


def detect_take_tasks(take: Take, model: str, device: str = "auto", boxes: dict[str, np.ndarray] | None = None,
                      cameras: Sequence[str] | None = None, chunk: int = 16, min_score: float = 0.5,
                      frames_per_task: int = 256, track: bool = True) -> list[DetectTask]:
    """A take's detection split by camera and frame range: whole chunks per task, so that every
    network call (and every run of the tracker) sees the frames it would in one pass over the
    camera. Frames past the end of a video cut short are in no task (they stay undetected)."""
    span = max(1, frames_per_task // chunk) * chunk
    return [DetectTask(str(take.path.resolve()), cam, start, min(start + span, n), model, device, chunk, min_score,
                       None if boxes is None else boxes[cam][start:start + span], track)
            for cam in (cameras or take.cameras) for n in (take.readable_frames(cam),) for start in range(0, n, span)]


def detect_tasks(take: Take, tasks: list[DetectTask], workers: int = 1, scheduler: str | None = None,
                 progress: Progress = silent) -> dict[str, CameraKeypoints]:
    """Run detect_take_tasks' tasks (inline, in `workers` processes or on the Dask `scheduler`) and
    put each camera's keypoints together; the first failed task's error is raised."""
    from ..tasks import run_tasks

    cameras = list(dict.fromkeys(t.camera for t in tasks))
    arrays = {cam: _empty(take.frame_count(cam)) for cam in cameras}
    total, done = sum(t.stop - t.start for t in tasks), 0
    progress("detect", done, total)
    for task, out in run_tasks(detect_range, tasks, workers, scheduler, key=_task_key):
        if isinstance(out, Exception):
            raise out
        for whole, part in zip(arrays[task.camera], out):
            whole[task.start:task.stop] = part
        done += task.stop - task.start
        progress("detect", done, total)
    return {cam: _camera_keypoints(*arrays[cam]) for cam in cameras}


def _task_key(task: DetectTask) -> str:
    return f"detect-{Path(task.take).name}-{task.camera}-{task.start}"


def _empty(frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints (F,21,3) NaN with confidence 0, boxes and angles (F,5) NaN: nothing found yet."""
    kp = np.full((frames, NUM_JOINTS, 3), np.nan, np.float32)
    kp[..., 2] = 0
    return kp, np.full((frames, 5), np.nan)


def _camera_keypoints(kp: np.ndarray, used: np.ndarray) -> CameraKeypoints:
    return CameraKeypoints(kp, used[:, :4].astype(np.float32), used[:, 4].astype(np.float32))


def _detect_frames(detector: Detector, frames, boxes: np.ndarray | None, chunk: int, min_score: float,
                   track: bool, kp: np.ndarray, used: np.ndarray, done: Callable[[int], None] = lambda n: None) -> None:
    """Detect `chunk` frames ((index, image) pairs) at a time into kp and used; done(frames) after
    each batch."""
    while batch := list(islice(frames, chunk)):
        if track and boxes is None:
            _track_batch(detector, batch, min_score, kp, used)
        else:
            _detect_batch(detector, batch, boxes, min_score, kp, used)
        done(len(batch))


def _detect_batch(detector: Detector, batch: list[tuple[int, np.ndarray]], boxes: np.ndarray | None,
                  min_score: float, kp: np.ndarray, used: np.ndarray) -> None:
    """Keypoints of a batch of (frame index, image) into kp (F,21,3), and the boxes and angles
    used into used (F,5): boxes (F,5) of the camera, or None for the palm detector's."""
    index = [k for k, _ in batch]
    images = [im for _, im in batch]
    if boxes is None:
        found_boxes, found_angles = detector.find_boxes(images, 1, min_score)
        given = np.full((len(batch), 5), np.nan)
        for i, (fb, fa) in enumerate(zip(found_boxes, found_angles)):
            if len(fb):
                given[i] = np.r_[fb[0], fa[0]]
    else:
        given = boxes[index]
    out = detector.detect_many(images, [g[None, :4] for g in given], [g[None, 4] for g in given])
    kp[index] = np.concatenate(out)
    used[index] = given


def _track_batch(detector: Detector, batch: list[tuple[int, np.ndarray]], min_score: float,
                 kp: np.ndarray, used: np.ndarray) -> None:
    """Keypoints of a batch of frames as MediaPipe's tracker finds them: the palm detector and two
    passes of the keypoint model on the batch's first frame and wherever the hand was lost (its
    presence below min_score), one pass on the crop around the previous frame's keypoints on every
    other frame. The batch starts afresh, so a take split into whole batches gives the same."""
    scale = detector.model.crop.box_scale
    previous = None
    for k, image in batch:
        found = None
        if previous is not None:
            rect = bx.rects_from_keypoints(previous[None])
            found = detector.detect_rects([image], [rect], refine=0)[0][0]
            # the box that, enlarged by the model's box scale, is the crop: as the palm's boxes
            given = np.r_[rect[0, :2] - rect[0, 2] / (2 * scale), rect[0, :2] + rect[0, 2] / (2 * scale), rect[0, 4]]
        if found is None or not found[0, 2] >= min_score:
            _detect_batch(detector, [(k, image)], None, min_score, kp, used)
            found, given = kp[k].astype(np.float64), used[k]
        kp[k], used[k] = found, given
        previous = found if found[0, 2] >= min_score and np.isfinite(found[:, :2]).all() else None


def write_keypoints_h5(path: str | Path, data: TakeKeypoints) -> None:
    """Write keypoints2d.h5 atomically: built in memory (a take's keypoints are megabytes), then
    written beside the target and renamed."""
    buffer = io.BytesIO()
    with h5py.File(buffer, "w") as f:
        f.attrs.update({"format": FORMAT, "version": 1, "model": data.model,
                        "model_file": data.model_file, "box_source": data.box_source,
                        "joint_names": list(JOINT_NAMES), **data.attrs})
        group = f.create_group("cameras")
        for cam, ck in data.cameras.items():
            g = group.create_group(cam)
            g.create_dataset("keypoints", data=ck.keypoints.astype(np.float32), compression="gzip")
            g.create_dataset("boxes", data=ck.boxes.astype(np.float32), compression="gzip")
            g.create_dataset("angles", data=ck.angles.astype(np.float32), compression="gzip")
    write_atomic(path, buffer.getvalue())


def read_keypoints_h5(path: str | Path) -> TakeKeypoints:
    """Read keypoints2d.h5; TakeError naming the file when it is not one."""
    path = Path(path)
    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("format") != FORMAT:
                raise TakeError(f"{path}: not a keypoints2d file "
                                f"(format attribute {f.attrs.get('format')!r})")
            cams = {cam: CameraKeypoints(g["keypoints"][()], g["boxes"][()], g["angles"][()])
                    for cam, g in f["cameras"].items()}
            attrs = {k: v for k, v in f.attrs.items()
                     if k not in ("model", "model_file", "box_source")}
            return TakeKeypoints(cams, str(f.attrs["model"]), str(f.attrs["model_file"]),
                                 str(f.attrs["box_source"]), attrs)
    except (FileNotFoundError, OSError) as exc:
        raise TakeError(f"{path}: cannot be read as HDF5 ({exc})") from None
