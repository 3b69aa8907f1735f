"""IK speed and accuracy: fit_hand against a plain scipy.optimize.least_squares per frame, side by side.

    .venv/bin/python benchmarks/bench_ik.py [--frames 240] [--scipy-frames 240] [--subject s02]

The workload of annotate: a simulated 53-camera grasp at 120 frames/s (1280x720, the simulated
detector with 2 px noise, 10% outliers and self-occlusion, triangulated by triangulate_frames),
fitted with the subject's true bone lengths. Measured on one core:

- fit_hand, all frames at once (closed-form start per frame; the default);
- fit_hand, warm-started frame by frame (init="previous"), the tracker a streaming user would run;
- scipy.optimize.least_squares per frame, the tool one would otherwise reach for: the same
  keypoint residuals (fingertips weighted 2, no robust loss), the joint limits as bounds
  (method "trf"), the default 2-point finite-difference Jacobian, warm-started from the previous
  frame's solution (the first frame from fit_hand's closed-form start, which it does not have).

Errors are against the true joints and angles (finger angles RMS; the global rotation by the
angle between rotations).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import timeit  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scipy.optimize import least_squares  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from dataset_tools.hand.ik import fit_hand  # noqa: E402
from dataset_tools.simulated_detector import SimulatedDetector  # noqa: E402
from dataset_tools.triangulation import triangulate_frames  # noqa: E402
from manus_core.skeleton import FINGERTIPS, HandSkeleton, rodrigues  # noqa: E402
from rig.layouts import make_rig  # noqa: E402
from rig.sim.cube import true_cameras  # noqa: E402
from rig.sim.hand import make_hand  # noqa: E402
from rig.sim.motion import make_motion  # noqa: E402
from rig.sim.objects import make_object  # noqa: E402


def workload(frames: int, subject: str) -> tuple[np.ndarray, np.ndarray, HandSkeleton]:
    rig = true_cameras(make_rig("cube53", resolution=(1280, 720)))
    hand = make_hand(subject)
    motion = make_motion("grasp", hand, make_object("mug"), frames / 120.0, seed=0)
    truth = motion.hand_angles(np.arange(frames) / 120.0)
    kp = SimulatedDetector(noise_px=2.0, outlier_rate=0.1, seed=1).detect(rig, hand.skeleton.forward(truth))
    joints, _ = triangulate_frames(rig, kp)
    return joints, truth, hand.skeleton


def scipy_per_frame(joints: np.ndarray, skeleton: HandSkeleton, first: np.ndarray) -> tuple[np.ndarray, int]:
    """least_squares frame by frame, warm-started; returns angles and the iterations (Jacobians)."""
    weights = np.ones(21)
    weights[list(FINGERTIPS)] = 2.0
    sqrt_w = np.sqrt(weights)[:, None]
    lower = np.where(np.isfinite(skeleton.lower), skeleton.lower, -np.inf)
    upper = np.where(np.isfinite(skeleton.upper), skeleton.upper, np.inf)
    out = np.empty((len(joints), 26))
    x = np.clip(first, lower + 1e-9, upper - 1e-9)
    iterations = 0
    for i, target in enumerate(joints):
        ok = np.isfinite(target).all(1)

        def residuals(p: np.ndarray) -> np.ndarray:
            return ((skeleton.forward(p) - target) * sqrt_w)[ok].ravel()

        result = least_squares(residuals, np.clip(x, lower, upper), bounds=(lower, upper), method="trf")
        x = result.x
        out[i] = x
        iterations += result.njev
    return out, iterations


def errors(angles: np.ndarray, truth: np.ndarray, skeleton: HandSkeleton) -> tuple[float, float, float]:
    joints_mm = 1e3 * np.nanmean(np.linalg.norm(skeleton.forward(angles) - skeleton.forward(truth), axis=-1))
    fingers = np.degrees(np.sqrt(np.nanmean((angles[:, 6:] - truth[:, 6:]) ** 2)))
    rel = np.swapaxes(rodrigues(angles[:, :3]), 1, 2) @ rodrigues(truth[:, :3])
    rotation = np.degrees(np.sqrt(np.mean(Rotation.from_matrix(rel).magnitude() ** 2)))
    return joints_mm, fingers, rotation


def timed(fn, repeat: int = 3):
    """(best of `repeat` runs in seconds, the result of one run)."""
    return min(timeit.repeat(fn, number=1, repeat=repeat)), fn()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=240)
    parser.add_argument("--scipy-frames", type=int, default=240)
    parser.add_argument("--subject", default="s02")
    args = parser.parse_args()
    joints, truth, skeleton = workload(args.frames, args.subject)
    bones = skeleton.bone_lengths
    print(f"grasp, {args.frames} frames at 120 frames/s, 53 cameras, 2 px noise + 10% outliers, triangulated; "
          f"subject {args.subject}; one core")
    rows = []
    t_batch, (a_batch, _, info_b) = timed(lambda: fit_hand(joints, bones, return_info=True))
    rows.append(("fit_hand, all frames at once", args.frames / t_batch, info_b.iterations.mean(),
                 *errors(a_batch, truth, skeleton)))
    t_seq, (a_seq, _, info_s) = timed(lambda: fit_hand(joints, bones, init="previous", return_info=True), repeat=2)
    rows.append(("fit_hand, warm start frame by frame", args.frames / t_seq, info_s.iterations.mean(),
                 *errors(a_seq, truth, skeleton)))
    n = min(args.scipy_frames, args.frames)
    t0 = time.perf_counter()
    a_sp, iterations = scipy_per_frame(joints[:n], skeleton, a_batch[0])
    t_sp = time.perf_counter() - t0
    rows.append((f"scipy least_squares per frame ({n} frames)", n / t_sp, iterations / n,
                 *errors(a_sp, truth[:n], skeleton)))
    print(f"{'method':<44} {'frames/s':>9} {'iter/frame':>10} {'joints mm':>9} {'fingers deg':>11} {'rot deg':>7}")
    for name, fps, it, mm, fing, rot in rows:
        print(f"{name:<44} {fps:>9.1f} {it:>10.1f} {mm:>9.3f} {fing:>11.3f} {rot:>7.3f}")
    print("(an iteration of scipy costs 27 residual evaluations for its finite-difference Jacobian)")
    print(f"speed-up over scipy: all frames at once x{rows[0][1] / rows[2][1]:.0f}, "
          f"warm-started frame by frame x{rows[1][1] / rows[2][1]:.0f}; goal 200 frames/s warm-started: "
          f"{'met' if rows[1][1] >= 200 else 'NOT met'} ({rows[1][1]:.0f})")


if __name__ == "__main__":
    main()
