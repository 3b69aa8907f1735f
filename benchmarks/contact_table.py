"""The contact comparison of docs/contacts.md: the demo on every subject x object x seed, MANUS-Hand
against the capsule template, IoU and F1 with their spread over seeds, and the camera ablation.

    python benchmarks/contact_table.py -o OUT [--subjects s01,s02,s03] [--objects mug,box]
                                       [--seeds 0,1] [--cameras 24] [--ablation 5,10,20,all]
                                       [--iterations 400] [--simulated-keypoints]

Each run is `manus-capture demo` with that subject, object and seed (the seed draws the rig's
cameras and clocks and the grasp); OUT/SUBJECT-OBJECT-SEED holds it. The runs of the first seed
also rebuild the models from fewer cameras (--ablation); the others use all cameras only.
--simulated-keypoints annotates from the simulated detector instead of the ONNX detector, as the
demo's flag of that name does (the tables of docs/contacts.md made before the ONNX detector became
the demo's default were made so).
A run already finished there is read back, not run again. Prints a markdown table per session and per
subject.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from manus_capture.demo import DemoConfig, run_demo


def _run(out: Path, subject: str, obj: str, seed: int, cameras: int, views: tuple[int, ...], iterations: int,
         simulated_keypoints: bool) -> dict:
    folder = out / f"{subject}-{obj}-{seed}"
    if (folder / "summary.json").exists():
        return json.loads((folder / "summary.json").read_text())
    print(f"== {folder.name}", flush=True)
    config = DemoConfig(cameras=cameras, subject=subject, object=obj, seed=seed, views=views,
                        object_iterations=iterations, hand_iterations=iterations,
                        simulated_keypoints=simulated_keypoints)
    return run_demo(folder, config, say=lambda line: print("   ", line, flush=True), force=True)


def _spread(values: list[float]) -> str:
    v = np.asarray(values)
    return f"{v.mean():.3f} ({v.min():.3f}-{v.max():.3f})" if len(v) > 1 else f"{v.mean():.3f}"


def _relative(ours: list[float], base: list[float]) -> str:
    return f"{100 * (np.mean(ours) / np.mean(base) - 1):+.0f} %"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-o", "--output", type=Path, required=True)
    parser.add_argument("--subjects", default="s01,s02,s03")
    parser.add_argument("--objects", default="mug,box")
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--cameras", type=int, default=24)
    parser.add_argument("--ablation", default="5,10,20,all")
    parser.add_argument("--iterations", type=int, default=DemoConfig.hand_iterations,
                        help="training steps of each Gaussian model (the demo's --iterations)")
    parser.add_argument("--simulated-keypoints", action="store_true",
                        help="the demo's ablation: keypoints from the simulated detector, not the ONNX detector")
    args = parser.parse_args()
    subjects, objects = args.subjects.split(","), args.objects.split(",")
    seeds = [int(s) for s in args.seeds.split(",")]
    ablation = tuple(0 if v == "all" else int(v) for v in args.ablation.split(","))
    runs = {(s, o, k): _run(args.output, s, o, k, args.cameras, ablation if k == seeds[0] else (0,), args.iterations,
                            args.simulated_keypoints)
            for s in subjects for o in objects for k in seeds}

    counts = sorted({int(c) for r in runs.values() for c in r["views"]})
    print("\n| subject | object | ours IoU | template IoU | relative | ours F1 | template F1 | "
          + " | ".join(f"{c} cams" for c in counts) + " |")
    print("|---" * (7 + len(counts)) + "|")
    for s in subjects:
        for o in objects:
            rs = [runs[s, o, k] for k in seeds]
            ours, base = [r["contact_iou"] for r in rs], [r["baseline_iou"] for r in rs]
            views = " | ".join(_spread([r["views"][str(c)] for r in rs if str(c) in r["views"]]) for c in counts)
            print(f"| {s} | {o} | {_spread(ours)} | {_spread(base)} | {_relative(ours, base)} "
                  f"| {_spread([r['contact_f1'] for r in rs])} | {_spread([r['baseline_f1'] for r in rs])} | {views} |")
    print("\n| subject | ours IoU | template IoU | relative (goal: >= +15 %) |")
    print("|---|---|---|---|")
    for s in subjects:
        ours = [runs[s, o, k]["contact_iou"] for o in objects for k in seeds]
        base = [runs[s, o, k]["baseline_iou"] for o in objects for k in seeds]
        print(f"| {s} | {np.mean(ours):.3f} | {np.mean(base):.3f} | {_relative(ours, base)} |")


if __name__ == "__main__":
    main()
