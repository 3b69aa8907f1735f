"""How refine's weights trade the finger angles against the fitted joints, on finished demos.

    python benchmarks/refine_weights.py DEMO [DEMO ...] [--iterations 0]
           [--set 'prior_deg=10,smooth_deg=3,keypoint_scale_px=3' --set 'prior_deg=30,...']

DEMO is the output folder of `manus-capture demo` (or of benchmarks/contact_table.py): its grasp
take is refined again from annotate's angles with each --set of RefineOptions (default: refine's
own weights, and the two that docs/refine.md compares with them), through the demo's hand
model, and scored against the simulator's truth as the demo scores it (finger angles RMS, fitted
joints' mean error). --iterations 0 runs the keypoint stage only (seconds a take);
the demo's default (20) adds the image terms. Prints one table row per demo and set, then the
mean over the demos.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from dataset_tools.calibration.formats import load_cameras
from manus_capture.pose_score import pose_errors, truth_at_groups
from manus_capture.refine import RefineOptions, fit_poses
from manus_capture.refine_views import pose_views
from manus_capture.splat.checkpoint import load_checkpoint
from manus_capture.splat.hand import HandGaussians
from manus_core.dataset import read_dataset, take_key

CANDIDATES = ("", "prior_deg=20,smooth_deg=2,keypoint_scale_px=3", "prior_deg=30,smooth_deg=2,keypoint_scale_px=4")


def _options(text: str, iterations: int) -> RefineOptions:
    """RefineOptions from NAME=VALUE,... (each value of its field's default's type)."""
    names = {f.name for f in dataclasses.fields(RefineOptions)}
    values = {}
    for item in filter(None, text.split(",")):
        name, _, value = item.partition("=")
        if name not in names:
            raise SystemExit(f"--set {text}: {name!r} is not a RefineOptions field")
        values[name] = type(getattr(RefineOptions, name))(value)
    return RefineOptions(**{"iterations": iterations, **values})


def _demo_rows(demo: Path, sets: list[str], iterations: int) -> list[tuple[float, float]]:
    take = next((demo / "session").glob("*-grasp*"))
    key = take_key(take)
    gaussians, extra, meta = load_checkpoint(demo / "models" / "hand.safetensors")
    model = HandGaussians.from_checkpoint(gaussians, extra)
    ann = read_dataset(demo / "DATASET.h5")[key]
    views = pose_views(take, demo / "DATASET.h5", ann, load_cameras(demo / "calib"), ann.joint_angles,
                       RefineOptions.margin, RefineOptions.scale)
    truth = truth_at_groups(take, ann.frame_ns)
    joints, angles = pose_errors(ann.bone_lengths, ann.joint_angles, truth)
    print(f"| {demo.name} | annotate | {angles:.2f} | {joints:.2f} |", flush=True)
    rows = []
    for text in sets:
        options = dataclasses.replace(_options(text, iterations), eps2d=float(meta.get("eps2d", 0.3)))
        result = fit_poses(model, ann.joint_angles, views, options)
        joints, angles = pose_errors(ann.bone_lengths, result.angles, truth)
        rows.append((angles, joints))
        print(f"| {demo.name} | {text or 'defaults'} | {angles:.2f} | {joints:.2f} |", flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("demos", type=Path, nargs="+")
    parser.add_argument("--set", dest="sets", action="append", help="RefineOptions fields, NAME=VALUE,...")
    parser.add_argument("--iterations", type=int, default=0, help="Adam steps with the image terms (0: keypoints)")
    args = parser.parse_args()
    sets = args.sets or list(CANDIDATES)
    print("| demo | weights | finger angles RMS (deg) | fitted joints (mm) |\n|---|---|---|---|")
    rows = np.array([_demo_rows(demo, sets, args.iterations) for demo in args.demos])   # (demos, sets, 2)
    for text, (angles, joints) in zip(sets, rows.mean(0)):
        print(f"| mean of {len(args.demos)} | {text or 'defaults'} | {angles:.2f} | {joints:.2f} |")


if __name__ == "__main__":
    main()
