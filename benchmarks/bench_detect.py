"""Hand keypoints on a recorded take: the palm detector in every frame against MediaPipe's tracking.

    .venv/bin/python benchmarks/bench_detect.py [--cameras 8] [--seconds 0.5] [--keep DIR]

The simulated cube records a grasp take at 1280x720 and 120 FPS (`--cameras` spread over the cube,
JPEG, each camera on its own clock). `detect_take` then runs on it five times, on one core with
one thread: `track=False`, the palm detector and two passes of the keypoint model in every frame;
`track=True` (the default; keypoints2d.track_frames), the palm detector afresh every 128 frames, where
the hand is lost and, while none is found, on one frame in 4 (the frames between tracked backwards
from where it finds the hand), one pass on the crop around the previous frame's keypoints elsewhere;
the tracker of earlier rounds beside it (afresh every 16 frames, the palm detector on every frame
without a hand: `redetect_every=16, search_every=1`); tracking with the palm detector looking at
square tiles of each frame too (`detect --palm-tiles`); tracking with
MediaPipe's lite keypoint model (`--model mediapipe-hand-lite`); and tracking with the full model
in int8 (`--model mediapipe-hand-int8`), calibrated by `models quantize` on another take (a second
subject, s03: a larger hand, darker skin; 4 cameras, 0.25 s) in a model cache of the benchmark's
own (benchmarks/int8_cache.py). All are scored against the simulator's true joints, projected at
each frame's true exposure (this is scoring code: it reads ground_truth.h5): the share of frames
whose true hand is in view that have a hand (presence >= 0.5), the median and 90th percentile over
those frames of the per-frame median joint error in pixels, and the median over the frames in which
every row found the hand (the rows find it in different frames, the hard ones counting against
whoever finds them). Printed beside them: frames per second on the core, and decoding the same
frames alone (`Take.iter_frames`), the floor of detect; the ratio of tracking's rate to the palm
detector's in every frame.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path

import cv2
import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parents[1]), str(Path(__file__).resolve().parent)]

from int8_cache import quantized_cache  # noqa: E402

from dataset_tools.keypoints.detector import Detector  # noqa: E402
from dataset_tools.keypoints.keypoints2d import REDETECT_EVERY, SEARCH_EVERY, detect_take  # noqa: E402
from dataset_tools.keypoints.models import load_model  # noqa: E402
from dataset_tools.keypoints.palm import PalmDetector  # noqa: E402
from dataset_tools.simulated_detector import exposure_times, joints_at  # noqa: E402
from manus_core.ground_truth import GroundTruth  # noqa: E402
from manus_core.take import Take  # noqa: E402
from rig.layouts import make_rig  # noqa: E402
from rig.record import record_take  # noqa: E402
from rig.sim.subject import with_sim_subject  # noqa: E402

PRESENT = 0.5


def record(root: Path, cameras: int, seconds: float, seed: int = 0, subject: str | None = None) -> Take:
    config = with_sim_subject(make_rig("cube53", cameras=cameras, resolution=(1280, 720), fps=120.0, seed=seed),
                              subject=subject)
    config = dataclasses.replace(config, sim=dataclasses.replace(config.sim, supersample=1))
    t = time.perf_counter()
    record_take(config, root, "grasp", "grasp", seconds)
    take = Take(root / "grasp")
    frames = sum(take.frame_count(c) for c in take.cameras)
    print(f"recorded {frames} frames of {cameras} cameras at 1280x720 in {time.perf_counter() - t:.0f} s", flush=True)
    return take


def true_pixels(take: Take) -> dict[str, np.ndarray]:
    """Per camera, the true joints (F,21,2) in its distorted pixels at each frame's exposure; NaN
    where the joint is behind the camera or out of the image."""
    gt = GroundTruth.of_take(take.path)
    rig = gt.cameras.rig()
    out = {}
    for cam in take.cameras:
        host = take.camera_frames(cam)["t_host_ns"].astype(np.float64)[:, None]
        exposure, _ = exposure_times(gt, (cam,), host)
        joints = joints_at(gt.frames.tick_ns, gt.hand.joints3d, exposure)[:, 0]      # (F,21,3)
        uv = rig.subset([cam]).project(joints.reshape(-1, 3))[0].reshape(-1, 21, 2)
        w, h = take.meta["resolution"]
        inside = (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h)
        out[cam] = np.where(inside[..., None], uv, np.nan)
    return out


def frame_errors(found: dict, truth: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Over every camera's frames: whether most of the true hand is in view, and the median joint
    error in px of the hand found (NaN where none was found or the hand is not in view)."""
    in_view, errors = [], []
    for cam, uv in truth.items():
        kp = found[cam].keypoints
        visible = np.isfinite(uv).all(axis=-1).sum(axis=1) >= 15          # most of the hand in the image
        with warnings.catch_warnings():        # frames without a hand: all NaN, and NaN they stay
            warnings.simplefilter("ignore", RuntimeWarning)
            err = np.nanmedian(np.linalg.norm(kp[..., :2] - uv, axis=-1), axis=1)
        in_view.append(visible)
        errors.append(np.where(visible & (kp[:, 0, 2] >= PRESENT), err, np.nan))
    return np.concatenate(in_view), np.concatenate(errors)


def timed(fn):
    start = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cameras", type=int, default=8)
    parser.add_argument("--seconds", type=float, default=0.5)
    parser.add_argument("--keep", type=Path, default=None, help="record the take here and keep it (reused if there)")
    args = parser.parse_args()
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    cv2.setNumThreads(1)
    root = args.keep or Path(tempfile.mkdtemp(prefix="bench_detect_"))
    try:
        take = Take(root / "grasp") if (root / "grasp" / "ground_truth.h5").exists() else \
            record(root, args.cameras, args.seconds)
        calibration = root / "calibration" / "grasp"
        if not (calibration / "ground_truth.h5").exists():
            record(calibration.parent, 4, 0.25, seed=1, subject="s03")
        quantized_cache(root, [calibration])
        truth = true_pixels(take)
        frames = sum(take.frame_count(c) for c in take.cameras)
        # twice: the first read also brings the videos into the page cache, where every run below finds them
        decode_s = [timed(lambda: [None for c in take.cameras for _ in take.iter_frames(c)])[1] for _ in range(2)][1]
        rates, errors = {}, {}
        default = dict(redetect_every=REDETECT_EVERY, search_every=SEARCH_EVERY)
        for name, model, track, tracker, tiles in (
                ("palm detector every frame", "mediapipe-hand", False, default, False),
                ("tracking as before", "mediapipe-hand", True, dict(redetect_every=16, search_every=1), False),
                ("tracking (default)", "mediapipe-hand", True, default, False),
                ("tracking, palm tiles", "mediapipe-hand", True, default, True),
                ("tracking, lite model", "mediapipe-hand-lite", True, default, False),
                ("tracking, int8 model", "mediapipe-hand-int8", True, default, False)):
            detector = Detector(load_model(model, device="cpu", threads=1),
                                palm=PalmDetector(device="cpu", threads=1, tiles=tiles))
            found, wall = timed(lambda: detect_take(take, detector, track=track, **tracker))
            rates[name] = frames / wall
            in_view, errors[name] = frame_errors(found, truth)
        # the rows find the hand in different frames: medians over each row's own, and over the frames all found
        common = np.logical_and.reduce([np.isfinite(e) for e in errors.values()])
        print(f"{'':<34} {'frames/s':>9} {'of decode':>10} {'hand found':>11} {'median px':>10} {'p90 px':>8} "
              f"{'median, all found':>18}")
        print(f"{'decode alone (Take.iter_frames)':<34} {frames / decode_s:>9.1f} {'100%':>10}")
        for name, e in errors.items():
            mine = e[np.isfinite(e)]
            share = len(mine) / max(in_view.sum(), 1)
            print(f"{name:<34} {rates[name]:>9.1f} {rates[name] * decode_s / frames:>10.0%} {share:>11.0%} "
                  f"{np.median(mine):>10.2f} {np.percentile(mine, 90):>8.2f} {np.median(e[common]):>18.2f}")
        ratio = rates["tracking (default)"] / rates["palm detector every frame"]
        before = rates["tracking (default)"] / rates["tracking as before"]
        print(f"\ntracking / palm detector every frame: {ratio:.2f}x the frames per second, / tracking as before: "
              f"{before:.2f}x ({frames} frames, {int(in_view.sum())} with the hand in view, {int(common.sum())} in "
              f"which every row found it)")
    finally:
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
