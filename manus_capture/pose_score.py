"""How far fitted hand poses lie from the simulator's true ones: scoring only.

The demo and the benchmarks score annotate's and refine's joint angles against a simulated
take's ground_truth.h5 with these; no stage of the pipeline reads the truth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from manus_core.ground_truth import GroundTruth
from manus_core.skeleton import HandSkeleton


def truth_at_groups(take: Path, frame_ns: np.ndarray) -> dict:
    """The simulator's joints (T,21,3), joint angles (T,26) at each frame group, and bone lengths."""
    gt = GroundTruth.of_take(take)
    hand = gt.hand
    tick = np.clip(gt.tick_at(frame_ns), 0, len(hand.joints3d) - 1)
    return {"joints3d": hand.joints3d[tick], "joint_angles": hand.joint_angles[tick],
            "bone_lengths": hand.bone_lengths}


def pose_errors(bone_lengths: np.ndarray, angles: np.ndarray, truth: dict) -> tuple[float, float]:
    """(fitted joints' mean error in mm, finger angles' RMS error in degrees) against the truth."""
    fitted = HandSkeleton(bone_lengths).forward(angles)
    fit = np.linalg.norm(fitted - truth["joints3d"], axis=-1)
    ang = np.degrees(angles[:, 6:] - truth["joint_angles"][:, 6:])
    return 1000 * float(np.nanmean(fit)), float(np.sqrt(np.nanmean(ang ** 2)))
