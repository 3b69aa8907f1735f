"""Pose refinement speed: frames per second at the demo's size, and on CUDA ours against gsplat.

    .venv/bin/python benchmarks/bench_refine.py                 # CPU, the demo's size
    python3 benchmarks/bench_refine.py --device cuda            # adds gsplat's rasterizer beside ours

What `manus-capture refine` does to the demo's grasp take (60 frame groups, 24 cameras, windows of
about 104x96 pixels around the hand at 320x180, MANUS-Hand as the builder makes it: 6.7k surfels),
on synthetic views: the builder's surfel hand is posed along a grasp-like motion, rendered into
`--cameras` cameras around it at the window size (the renders are the images, alpha > 0.5 the
masks, its projected joints with 2 px of noise the keypoints), and the poses, perturbed by 5 deg,
are refined with RefineOptions' defaults. Printed: frames per second of the whole refinement and
of its keypoint stage alone. With `--device cuda` the same runs with backend="torch" (ours) and
backend="gsplat", with the ratio and the peak CUDA memory of each.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import replace

import numpy as np
import torch

from manus_capture.builder import surface_hand
from manus_capture.refine import RefineOptions, fit_poses
from manus_capture.refine_views import PoseViews
from manus_capture.splat.rasterize import gsplat_available
from manus_capture.splat.synthetic import look_at
from manus_capture.splat.trainer import SURFACE_EPS2D


def scene(frames: int, cameras: int, width: int, height: int, device: str) -> tuple:
    """The surfel hand, its true motion (frames,26) and PoseViews of it."""
    model = surface_hand(None).to(device)
    sk = model.skeleton
    mid = (np.nan_to_num(sk.lower, neginf=0.0) + np.nan_to_num(sk.upper, posinf=0.0)) / 2
    mid[:6] = 0
    t = np.linspace(0, 1, frames)[:, None]
    truth = mid * (0.2 + 0.5 * t)
    centre = torch.as_tensor(sk.forward(truth[0]).mean(0), dtype=torch.float32)
    eyes = [centre + 0.45 * torch.tensor([math.cos(a), math.sin(a), 0.3 + 0.4 * (i % 2)])
            for i, a in enumerate(np.linspace(0, 2 * math.pi, cameras, endpoint=False))]
    viewmats = torch.stack([look_at(e, centre) for e in eyes]).to(device)
    f = 0.45 * width    # the hand covers a tenth of the window, as in the demo
    Ks = torch.tensor([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]]).repeat(cameras, 1, 1).to(device)
    views = PoseViews.rendered(model, truth, viewmats, Ks, width, height, keypoint_noise_px=2.0, outlier_rate=0.1,
                               eps2d=SURFACE_EPS2D)
    return model, truth, views


def run(model, truth, views, options: RefineOptions, device: str) -> dict:
    rng = np.random.default_rng(0)
    start = truth + np.radians(5.0) * rng.standard_normal(truth.shape) * (np.arange(26) >= 6)
    if device == "cuda":
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    result = fit_poses(model, start, views, options)
    if device == "cuda":
        torch.cuda.synchronize()
    seconds = time.perf_counter() - t0
    err = lambda a: float(np.degrees(np.sqrt(np.mean((a[:, 6:] - truth[:, 6:]) ** 2))))  # noqa: E731
    out = {"frames_per_s": len(truth) / seconds, "seconds": seconds, "finger_rms_deg_before": err(start),
           "finger_rms_deg_after": err(result.angles), "diverged": result.frames_diverged}
    if device == "cuda":
        out["peak_cuda_mb"] = torch.cuda.max_memory_allocated() / 2 ** 20
    return out


@torch.no_grad()
def agreement(model, truth: np.ndarray, views: PoseViews, device: str) -> float:
    """Largest difference of the two rasterizers' renders of one frame per camera (one pose per
    camera, the batched path of rasterize), in [0,1] colour units."""
    C = len(views.cam_viewmats)
    angles = torch.as_tensor(truth[np.arange(C) % len(truth)], dtype=torch.float32, device=device)
    w, h = views.size
    args = (angles, views.cam_viewmats.to(device), views.cam_Ks.to(device), w, h)
    ours, _ = model.render(*args, eps2d=SURFACE_EPS2D, backend="torch")
    theirs, _ = model.render(*args, eps2d=SURFACE_EPS2D, backend="gsplat")
    return float((ours - theirs).abs().max())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--cameras", type=int, default=24)
    parser.add_argument("--size", default="104x96", help="window WxH")
    parser.add_argument("--iterations", type=int, default=RefineOptions.iterations)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    w, h = (int(x) for x in args.size.split("x"))
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, device {args.device}")
    model, truth, views = scene(args.frames, args.cameras, w, h, args.device)
    print(f"MANUS-Hand surfels: {len(model)} Gaussians; {args.frames} frames x {args.cameras} cameras, "
          f"windows {w}x{h}")
    base = RefineOptions(iterations=args.iterations, eps2d=SURFACE_EPS2D, backend="torch")
    rows = {"keypoint stage": run(model, truth, views, replace(base, iterations=0), args.device),
            "refine (ours)": run(model, truth, views, base, args.device)}
    if args.device == "cuda" and gsplat_available():
        print(f"ours vs gsplat, one pose per camera: renders differ by at most "
              f"{agreement(model, truth, views, args.device):.3f}")
        rows["refine (gsplat)"] = run(model, truth, views, replace(base, backend="gsplat"), args.device)
    elif args.device == "cuda":
        print("gsplat: not installed, not compared")
    else:
        print("gsplat: not compared (it needs CUDA; this run is on the CPU)")
    for name, r in rows.items():
        mem = f", peak CUDA {r['peak_cuda_mb']:.0f} MB" if "peak_cuda_mb" in r else ""
        print(f"{name}: {r['frames_per_s']:.2f} frames/s ({r['seconds']:.1f} s){mem}; finger angles "
              f"{r['finger_rms_deg_before']:.2f} -> {r['finger_rms_deg_after']:.2f} deg RMS, "
              f"{r['diverged']} diverged")
    if "refine (gsplat)" in rows:
        ratio = rows["refine (gsplat)"]["frames_per_s"] / rows["refine (ours)"]["frames_per_s"]
        print(f"ratio gsplat/ours: {ratio:.1f}x")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
