"""Where a take's 2D keypoints come from, for annotate: TAKE/keypoints2d.h5 (`detect`'s file), the
ONNX detector run now (its output written to keypoints2d.h5 as `detect` writes it), or the
simulated detector (an ablation that reads the simulated take's ground truth, used only when
named). Keypoints come back per frame group, (T,C,21,3) in the take's camera order.
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence

import numpy as np

from manus_core.dataset import software_version
from manus_core.errors import AnnotateError
from manus_core.take import Take

from .annotate_options import AnnotateOptions
from .keypoints.keypoints2d import (
    TakeKeypoints,
    box_source,
    cached_detector,
    detect_take,
    keypoints_model,
    read_keypoints_h5,
    write_keypoints_h5,
)
from .simulated_detector import SimulatedDetector, simulated_take_keypoints


def _gather(per_camera: Sequence[np.ndarray | None], frame_index: np.ndarray) -> np.ndarray:
    """(T,C,21,3) keypoints of each group from per-camera (F_c,21,3) arrays (None: camera absent)."""
    out = np.full(frame_index.shape + (21, 3), np.nan)
    out[..., 2] = 0.0
    for c, kp in enumerate(per_camera):
        if kp is None:
            continue
        idx = frame_index[:, c]
        ok = (idx >= 0) & (idx < len(kp))
        out[ok, c] = kp[idx[ok]]
    return out


def _keypoints_file(take: Take, frame_index: np.ndarray) -> tuple[np.ndarray, str]:
    path = take.path / "keypoints2d.h5"
    data = read_keypoints_h5(path)
    for cam in take.cameras:
        if cam in data.cameras and len(data.cameras[cam].keypoints) != take.frame_count(cam):
            raise AnnotateError(f"{path}: camera {cam} has {len(data.cameras[cam].keypoints)} frames of keypoints, "
                                f"frames.csv {take.frame_count(cam)} (detected on another recording?)")
    per_camera = [data.cameras[c].keypoints if c in data.cameras else None for c in take.cameras]
    return _gather(per_camera, frame_index), f"file:keypoints2d.h5 (model {data.model})"


def _keypoints_detect(take: Take, frame_index: np.ndarray, options: AnnotateOptions) -> tuple[np.ndarray, str]:
    detector = cached_detector(options.model, options.device, options.palm_tiles)
    result = detect_take(take, detector)
    write_keypoints_h5(take.path / "keypoints2d.h5", TakeKeypoints(
        result, detector.name, str(detector.model.session.path), box_source(None, True, options.palm_tiles),
        {"take": str(take.path), "software": software_version(), "providers": ",".join(detector.providers)}))
    tiles = "+palm-tiles" if options.palm_tiles else ""
    return _gather([result[c].keypoints for c in take.cameras], frame_index), f"detect:{options.model}{tiles}"


def _keypoints_simulated(take: Take, frame_index: np.ndarray, options: AnnotateOptions) -> tuple[np.ndarray, str]:
    # Each take gets its own noise: the same seed on two takes would repeat the same faults.
    seed = options.sim_seed ^ zlib.crc32(take.path.name.encode())
    det = SimulatedDetector(options.sim_noise_px, options.sim_outlier_rate, dropout_rate=options.sim_dropout_rate,
                            seed=seed)
    return simulated_take_keypoints(take, frame_index, det), (
        f"simulated:noise_px={options.sim_noise_px},outlier_rate={options.sim_outlier_rate},"
        f"dropout_rate={options.sim_dropout_rate},seed={seed}")


def keypoint_mode(take: Take, options: AnnotateOptions) -> str:
    """file, detect or simulated: what options.keypoints means for this take."""
    if options.keypoints == "auto":
        return "file" if (take.path / "keypoints2d.h5").exists() else "detect"
    return options.keypoints


def cross_view_model(take: Take, options: AnnotateOptions) -> str | None:
    """The keypoint model annotate's cross-view step runs on this take (cross_view.py), or None:
    with `cross_view`, the model it detects with, or with keypoints from keypoints2d.h5 the `model`
    of the options where the file was detected with it (by `detect` or an earlier annotate), so that
    a second run reading the file gives what the first gave. Another model's keypoints, or a
    simulation's, are used as they are."""
    if not options.cross_view:
        return None
    mode = keypoint_mode(take, options)
    if mode == "detect" or mode == "file" and keypoints_model(take.path / "keypoints2d.h5") == options.model:
        return options.model
    return None


def take_keypoints(take: Take, frame_index: np.ndarray,
                   options: AnnotateOptions = AnnotateOptions()) -> tuple[np.ndarray, str]:
    """Keypoints (T,C,21,3) of the take's frame groups and a description of where they came from."""
    mode = keypoint_mode(take, options)
    if mode == "file":
        if not (take.path / "keypoints2d.h5").exists():
            raise AnnotateError(f"{take.path / 'keypoints2d.h5'}: missing (run `manus-capture detect {take.path}`)")
        return _keypoints_file(take, frame_index)
    if mode == "simulated":
        return _keypoints_simulated(take, frame_index, options)
    return _keypoints_detect(take, frame_index, options)
