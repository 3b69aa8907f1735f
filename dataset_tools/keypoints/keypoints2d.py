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
a hand. Without it, MediaPipe's palm detector finds the hand and, by default, the hand is tracked
(`track_frames`): each frame is cropped around the previous frame's keypoints, as MediaPipe's
tracker runs, and the palm detector looks afresh every `redetect_every` frames and where the hand
is lost (`track=False`: the palm detector in every frame).
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
from manus_core.take import EncodedFrame, Take

from . import boxes as bx
from .detector import Detector, hand_keypoint_detector
from .models import JOINT_NAMES, NUM_JOINTS

FORMAT = "manus-capture keypoints2d"
# The tracker starts afresh (the palm detector) at every multiple of this many frames of a camera,
# and a task holds whole periods: a take split over tasks gives the keypoints of one pass.
REDETECT_EVERY = 128
Frame = np.ndarray | EncodedFrame   # an image (H,W,3) BGR uint8, or a take's frame decoded on demand
# While no hand is found the palm detector looks at one frame in this many, not at every frame: a
# camera that does not see the hand costs little more than its decoding. Where it finds the hand,
# the frames skipped since its last look are tracked backwards from there. (On bench_detect's
# grasp, where the palm detector finds hands seen edge-on in single frames only, one in 4 found as
# many frames as one in 1 did, one in 8 a tenth fewer.)
SEARCH_EVERY = 4


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


def box_source(boxes: str | Path | None, track: bool, palm_tiles: bool = False) -> str:
    """keypoints2d.h5's `box_source`: file:PATH, palm-detector+tracking or palm-detector (with
    +tiles where the palm detector looked at square tiles too)."""
    if boxes:
        return f"file:{boxes}"
    return ("palm-detector+tiles" if palm_tiles else "palm-detector") + ("+tracking" if track else "")


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
                progress: Progress = silent, track: bool = True, redetect_every: int = REDETECT_EVERY,
                search_every: int = SEARCH_EVERY) -> dict[str, CameraKeypoints]:
    """Keypoints of every frame of the given cameras (default: all).

    boxes: per camera (F,5) as load_boxes gives (`chunk` frames per network call); None: the palm
    detector finds one hand, in every frame (likewise in chunks), or with `track` as track_frames
    does (one pass of the keypoint model a frame where the hand is tracked). Reports
    progress("detect", frames done, frames of all the cameras). Frames past the end of a video cut
    short (Take.missing_frames) stay undetected.
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
        _detect_frames(detector, take.iter_encoded(cam, 0, take.readable_frames(cam)),
                       None if boxes is None else boxes[cam], chunk, min_score, track, kp, used, batch_done,
                       redetect_every, search_every)
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
    track: bool = True         # with the palm detector: track from frame to frame (track_frames)
    redetect_every: int = REDETECT_EVERY
    palm_tiles: bool = False   # the palm detector also looks at square tiles of wide frames


_DETECTORS: dict[tuple[str, str, bool], Detector] = {}


def cached_detector(model: str, device: str = "auto", palm_tiles: bool = False) -> Detector:
    """The process's Detector of these settings, loaded on the first call (a worker runs many tasks)."""
    which = model, device, palm_tiles
    if which not in _DETECTORS:
        _DETECTORS[which] = hand_keypoint_detector(model, device=device, palm_tiles=palm_tiles)
    return _DETECTORS[which]


def detect_range(task: DetectTask) -> tuple[np.ndarray, np.ndarray]:
    """(keypoints (n,21,3), boxes and angles used (n,5)) of a DetectTask's frames."""
    kp, used = _empty(task.stop - task.start)
    # indices within the task, which starts on a whole redetection period (detect_take_tasks)
    frames = ((k - task.start, frame) for k, frame in Take(task.take).iter_encoded(task.camera, task.start, task.stop))
    _detect_frames(cached_detector(task.model, task.device, task.palm_tiles), frames, task.boxes, task.chunk,
                   task.min_score, task.track, kp, used, redetect_every=task.redetect_every)
    return kp, used


def detect_take_tasks(take: Take, model: str, device: str = "auto", boxes: dict[str, np.ndarray] | None = None,
                      cameras: Sequence[str] | None = None, chunk: int = 16, min_score: float = 0.5,
                      frames_per_task: int = 256, track: bool = True,
                      redetect_every: int = REDETECT_EVERY, palm_tiles: bool = False) -> list[DetectTask]:
    """A take's detection split by camera and frame range: whole chunks per task (when tracking,
    whole redetection periods), so that every network call and every run of the tracker sees the
    frames it would in one pass over the camera. Frames past the end of a video cut short are in no
    task (they stay undetected)."""
    unit = redetect_every if track and boxes is None else chunk
    span = max(1, frames_per_task // unit) * unit
    return [DetectTask(str(take.path.resolve()), cam, start, min(start + span, n), model, device, chunk, min_score,
                       None if boxes is None else boxes[cam][start:start + span], track, redetect_every, palm_tiles)
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
                   track: bool, kp: np.ndarray, used: np.ndarray, done: Callable[[int], None] = lambda n: None,
                   redetect_every: int = REDETECT_EVERY, search_every: int = SEARCH_EVERY) -> None:
    """Detect (index, frame) pairs into kp and used, `chunk` frames at a time; done(frames) after
    each chunk. With `track` and no boxes, track_frames. A frame: an image (H,W,3) BGR uint8 or a
    take's EncodedFrame."""
    if track and boxes is None:
        track_frames(detector, frames, min_score, kp, used, redetect_every, search_every, chunk, done)
        return
    while batch := list(islice(frames, chunk)):
        _detect_batch(detector, batch, boxes, min_score, kp, used)
        done(len(batch))


def _detect_batch(detector: Detector, batch: list[tuple[int, Frame]], boxes: np.ndarray | None,
                  min_score: float, kp: np.ndarray, used: np.ndarray) -> None:
    """Keypoints of a batch of (frame index, frame) into kp (F,21,3), and the boxes and angles
    used into used (F,5): boxes (F,5) of the camera, or None for the palm detector's."""
    index = [k for k, _ in batch]
    images = [frame if isinstance(frame, np.ndarray) else frame.decode() for _, frame in batch]
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


def track_frames(detector: Detector, frames, min_score: float, kp: np.ndarray, used: np.ndarray,
                 redetect_every: int = REDETECT_EVERY, search_every: int = SEARCH_EVERY, report_every: int = 16,
                 done: Callable[[int], None] = lambda n: None) -> None:
    """Keypoints of (index, frame) pairs (as _detect_frames), in order, as MediaPipe's tracker finds
    them, into kp and used.

    Where the hand was found in the previous frame (presence >= min_score), one pass of the keypoint
    model on the crop around its keypoints (of an EncodedFrame, only the window under the crop is
    decoded: the same pixels). Elsewhere the palm detector and two passes: at every
    index that is a multiple of `redetect_every` (a fresh start, so that a take split into whole
    periods gives the same), at the frame where the tracked hand is lost, and, while no hand is
    found, at one index in `search_every` and at the last frame of a period; where it finds the hand,
    the frames it skipped are tracked backwards from there. done(frames) every `report_every` frames.
    (redetect_every=16, search_every=1: as the tracker of earlier rounds.)
    """
    previous = None                    # the last frame's keypoints while the hand is tracked
    skipped: list[tuple[int, Frame]] = []   # frames not yet searched while no hand is found
    count = 0

    def search(k: int, frame: Frame) -> None:
        nonlocal previous, skipped
        _detect_batch(detector, [(k, frame)], None, min_score, kp, used)
        previous = _tracked(kp[k], min_score)
        if previous is not None:
            _track_backwards(detector, skipped, previous, min_score, kp, used)
        skipped = []

    for k, frame in frames:
        if k % redetect_every == 0:
            if skipped:
                search(*skipped.pop())
            previous, skipped = None, []
        if previous is not None:
            found, given = _track_one(detector, frame, previous)
            previous = _tracked(found, min_score)
            if previous is not None:
                kp[k], used[k] = found, given
            else:
                search(k, frame)          # lost here: look at once
        elif k % search_every == 0 or k % redetect_every == 0:
            search(k, frame)
        else:
            skipped.append((k, frame))
        count += 1
        if count % report_every == 0:
            done(report_every)
    if skipped:
        search(*skipped.pop())
    if count % report_every:
        done(count % report_every)


def _tracked(keypoints: np.ndarray, min_score: float) -> np.ndarray | None:
    """Keypoints (21,3) to track from, or None where the hand is not (presence under min_score, NaN)."""
    keypoints = np.asarray(keypoints, np.float64)
    return keypoints if keypoints[0, 2] >= min_score and np.isfinite(keypoints[:, :2]).all() else None


def _track_one(detector: Detector, frame: Frame, previous: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One pass on the crop around `previous` keypoints: (keypoints (21,3), used box and angle (5,))."""
    scale = detector.model.crop.box_scale
    rect = bx.rects_from_keypoints(previous[None])
    image = frame if isinstance(frame, np.ndarray) else frame.decode_window(*_window(rect[0]))
    found = detector.detect_rects([image], [rect], refine=0)[0][0]
    # the box that, enlarged by the model's box scale, is the crop: as the palm's boxes
    given = np.r_[rect[0, :2] - rect[0, 2] / (2 * scale), rect[0, :2] + rect[0, 2] / (2 * scale), rect[0, 4]]
    return found, given


def _window(rect: np.ndarray, margin: int = 2) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1): the frame's pixels a crop of `rect` (5,) reads, with `margin` more for its
    bilinear neighbours."""
    cx, cy, w, h, angle = rect
    c, s = abs(np.cos(angle)), abs(np.sin(angle))
    hx, hy = (w * c + h * s) / 2, (w * s + h * c) / 2
    return (int(np.floor(cx - hx)) - margin, int(np.floor(cy - hy)) - margin,
            int(np.ceil(cx + hx)) + margin + 1, int(np.ceil(cy + hy)) + margin + 1)


def _track_backwards(detector: Detector, skipped: list[tuple[int, Frame]], start: np.ndarray,
                     min_score: float, kp: np.ndarray, used: np.ndarray) -> None:
    """Track from keypoints `start` back through the skipped frames (latest first) while the hand
    stays found."""
    previous = start
    for k, frame in reversed(skipped):
        found, given = _track_one(detector, frame, previous)
        previous = _tracked(found, min_score)
        if previous is None:
            return
        kp[k], used[k] = found, given


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


def keypoints_model(path: str | Path) -> str | None:
    """The `model` a keypoints2d.h5 was detected with (its attributes only), None where the file is
    missing or not one."""
    try:
        with h5py.File(path, "r") as f:
            return str(f.attrs["model"]) if f.attrs.get("format") == FORMAT else None
    except (OSError, KeyError):
        return None


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
