"""Benchmarks of the bundled Gaussian splatting trainer (manus_capture.splat).

    .venv/bin/python benchmarks/bench_splat.py                # everything
    .venv/bin/python benchmarks/bench_splat.py --only lego    # accuracy on real data
    .venv/bin/python benchmarks/bench_splat.py --only step    # training-step speed and memory

lego: NeRF-synthetic "lego" (25 views with exact poses, ../shared/data/nerf_synthetic_lego_subset),
composited on white at full resolution and then reduced by area averaging; 20 views train the
object model (masks: alpha > 0, for the visual-hull initialization and mask pruning), every fifth
view is held out; PSNR and SSIM on the held-out views (goal: >= 24 dB).

step: one training step (render + L1 + backward) of random Gaussians in one camera, each in a
fresh process for its peak memory. CPU: 10k Gaussians at 256x256 and 100k at 512x512 (peak
resident memory). GPU, only when CUDA is available (`--device cuda`, the default there): 300k
Gaussians at 1280x720 as well, in steps per second and peak CUDA memory. gsplat, the tool a user
would otherwise pick, needs CUDA: it is timed side by side when it imports and the device is
CUDA, with the ratio, and the script says so otherwise. As a CPU baseline the dense brute-force
renderer (manus_capture.splat.reference) renders a scene small enough for it.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from manus_capture.splat import rasterize
from manus_capture.splat.losses import LossWeights, metric_lpips
from manus_capture.splat.rasterize import gsplat_available
from manus_capture.splat.reference import render_reference
from manus_capture.splat.strategy import DensifyStrategy
from manus_capture.splat.trainer import ObjectConfig, Views, evaluate, train_object

REPO = Path(__file__).resolve().parents[1]
STEP_SIZES = ((10_000, 256, 256), (100_000, 512, 512))
GPU_STEP_SIZES = ((300_000, 1280, 720),)
LEGO = REPO.parent / "shared" / "data" / "nerf_synthetic_lego_subset"


def load_lego(size: int):
    """Views of the lego subset at size x size on white, with masks where alpha > 0."""
    meta = json.loads((LEGO / "transforms_train.json").read_text())
    images, alphas, viewmats = [], [], []
    for frame in meta["frames"]:
        rgba = np.asarray(Image.open(LEGO / (frame["file_path"].removeprefix("./") + ".png")).convert("RGBA"),
                          dtype=np.float32) / 255
        factor = rgba.shape[0] // size
        rgb = rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:])  # composite on white first
        block = (size, factor, size, factor)
        images.append(rgb.reshape(*block, 3).mean(axis=(1, 3)))
        alphas.append(rgba[..., 3].reshape(block).mean(axis=(1, 3)))
        c2w = np.array(frame["transform_matrix"], dtype=np.float64)
        c2w[:3, 1:3] *= -1  # Blender camera axes (y up, looking along -z) -> OpenCV (y down, +z)
        viewmats.append(np.linalg.inv(c2w))
    f = 0.5 * size / math.tan(0.5 * meta["camera_angle_x"])
    c = size / 2 - 0.5  # pixel centres at integer coordinates
    K = torch.tensor([[f, 0, c], [0, f, c], [0, 0, 1]], dtype=torch.float32).repeat(len(images), 1, 1)
    masks = torch.tensor(np.stack(alphas)) > 0
    return Views(torch.tensor(np.stack(images)), K, torch.tensor(np.stack(viewmats), dtype=torch.float32), masks)


def bench_lego(size: int, iterations: int, points: int, sh_degree: int, device: str) -> dict:
    if not LEGO.is_dir():
        return {"skipped": f"no data at {LEGO}"}
    views = load_lego(size).to(device)
    test = list(range(0, len(views), 5))
    train = [i for i in range(len(views)) if i not in test]
    # the loss the figures in docs/splat.md were measured with: the paper's without LPIPS (the default
    # config adds it when `models install lpips-alex` has run)
    cfg = ObjectConfig(iterations=iterations, sh_degree=sh_degree, sh_increase_every=max(iterations // 4, 1),
                       init_points=points, background=(1.0, 1.0, 1.0), weights=LossWeights(lpips=0.0),
                       densify=DensifyStrategy(refine_start_iter=iterations // 10, refine_stop_iter=int(iterations * 0.7),
                                               refine_every=100, reset_every=max(iterations // 3, 1000)))
    t0 = time.perf_counter()
    result = train_object(views.subset(train), cfg)
    seconds = time.perf_counter() - t0
    lpips = metric_lpips()
    scores = evaluate(result.gaussians, views.subset(test), background=(1.0, 1.0, 1.0),
                      lpips=None if lpips is None else lpips.to(device))
    train_scores = evaluate(result.gaussians, views.subset(train), background=(1.0, 1.0, 1.0))
    return {"size": size, "iterations": iterations, "gaussians": len(result.gaussians), "train_s": seconds,
            "held_out_psnr": scores["psnr"], "held_out_ssim": scores["ssim"], "held_out_lpips": scores.get("lpips"),
            "train_psnr": train_scores["psnr"]}


def random_gaussians(n: int, device: str, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * 1.0
    quats = torch.randn(n, 4, generator=g)
    # Sized like a trained model: n Gaussians tile the unit cube's surface area seen by the camera.
    scales = (torch.rand(n, 3, generator=g) * 0.5 + 0.5) * (2.0 / math.sqrt(n))
    opacities = torch.rand(n, generator=g) * 0.8 + 0.1
    colors = torch.rand(n, 3, generator=g)
    return [x.to(device) for x in (means, quats, scales, opacities, colors)]


def camera(width: int, device: str, height: int | None = None):
    """A camera 2 units in front of the unit cube; the cube fills the shorter image side."""
    height = width if height is None else height
    f = min(width, height) * 1.2
    V = torch.eye(4)[None].clone()
    V[0, 2, 3] = 2.0
    K = torch.tensor([[[f, 0, width / 2 - 0.5], [0, f, height / 2 - 0.5], [0, 0, 1]]])
    return V.to(device), K.to(device)


def step_child(n: int, width: int, height: int, device: str, backend: str, repeats: int) -> None:
    """Run in a fresh process: time forward+backward and print JSON with the peak memory."""
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    params = [p.requires_grad_() for p in random_gaussians(n, device)]
    V, K = camera(width, device, height)
    target = torch.rand(1, height, width, 3, device=device)
    times = []
    for _ in range(repeats + 1):
        if device == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        rgb, _ = rasterize(*params, V, K, width, height, backend=backend)
        (rgb - target).abs().mean().backward()
        if device == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
        for p in params:
            p.grad = None
    out = {"n": n, "size": f"{width}x{height}", "backend": backend, "device": device, "step_s": float(np.median(times[1:])),
           "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
           "rss_after_imports_mb": base / 1024,
           "threads": torch.get_num_threads()}
    if device == "cuda":
        out["peak_cuda_mb"] = torch.cuda.max_memory_allocated() / 2 ** 20
    print(json.dumps(out))


def bench_step(device: str, repeats: int) -> list[dict]:
    rows = []
    backends = ["torch"] + (["gsplat"] if device == "cuda" and gsplat_available() else [])
    for n, width, height in STEP_SIZES + (GPU_STEP_SIZES if device == "cuda" else ()):
        for backend in backends:
            cmd = [sys.executable, __file__, "--child", str(n), str(width), str(height), device, backend,
                   str(repeats)]
            out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
            rows.append(json.loads(out.strip().splitlines()[-1]))
    return rows


def bench_reference(device: str) -> dict:
    """The tile rasterizer against the dense reference on a scene the reference can afford."""
    params = random_gaussians(300, "cpu", seed=1)
    V, K = camera(64, "cpu")
    t0 = time.perf_counter()
    ref, _ = render_reference(*params, V, K, 64, 64)
    t_ref = time.perf_counter() - t0
    t0 = time.perf_counter()
    rgb, _ = rasterize(*params, V, K, 64, 64)
    t_tile = time.perf_counter() - t0
    return {"n": 300, "size": 64, "reference_s": t_ref, "tiles_s": t_tile, "speedup": t_ref / t_tile,
            "max_abs_diff": float((rgb - ref).abs().max())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", choices=["lego", "step", "reference"], action="append")
    parser.add_argument("--size", type=int, default=100, help="lego image size (800 / size must be an integer)")
    parser.add_argument("--iterations", type=int, default=1500)
    parser.add_argument("--points", type=int, default=15_000, help="initial Gaussians in the visual hull")
    parser.add_argument("--sh-degree", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--child", nargs=6, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        n, width, height, device, backend, repeats = args.child
        step_child(int(n), int(width), int(height), device, backend, int(repeats))
        return
    todo = args.only or ["reference", "step", "lego"]
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, device {args.device}")
    if not (args.device == "cuda" and gsplat_available()):
        print("gsplat: not compared (it needs CUDA and the gsplat package; this run has "
              f"device={args.device}, gsplat {'installed' if gsplat_available() else 'not installed'})")
    if "reference" in todo:
        r = bench_reference(args.device)
        print(f"dense reference vs tiles, {r['n']} Gaussians at {r['size']}x{r['size']}: "
              f"{r['reference_s']:.3f} s vs {r['tiles_s']:.3f} s, ratio {r['speedup']:.1f}x, "
              f"max |diff| {r['max_abs_diff']:.1e}")
    if "step" in todo:
        rows = bench_step(args.device, args.repeats)
        for r in rows:
            extra = f", peak CUDA {r['peak_cuda_mb']:.0f} MB" if "peak_cuda_mb" in r else ""
            print(f"train step {r['backend']:6s} {r['n']:>7d} Gaussians {r['size']} on {r['device']} "
                  f"({r['threads']} threads): {r['step_s']:.3f} s ({1 / r['step_s']:.1f} steps/s), "
                  f"peak RSS {r['peak_rss_mb']:.0f} MB (imports alone {r['rss_after_imports_mb']:.0f} MB){extra}")
        by = {(r["n"], r["backend"]): r["step_s"] for r in rows}
        for n, _, _ in STEP_SIZES + GPU_STEP_SIZES:
            if (n, "gsplat") in by:
                print(f"  ratio torch/gsplat at {n}: {by[(n, 'torch')] / by[(n, 'gsplat')]:.1f}x")
        if args.device != "cuda":
            print("GPU section (300k Gaussians at 1280x720): not run, CUDA is not available")
    if "lego" in todo:
        r = bench_lego(args.size, args.iterations, args.points, args.sh_degree, args.device)
        if "skipped" in r:
            print(f"lego: skipped ({r['skipped']})")
        else:
            verdict = "meets" if r["held_out_psnr"] >= 24 else "misses"
            print(f"lego {r['size']}x{r['size']}, {r['iterations']} iterations, {r['gaussians']} Gaussians, "
                  f"{r['train_s']:.0f} s: held-out PSNR {r['held_out_psnr']:.2f} dB, SSIM {r['held_out_ssim']:.3f}, "
                  + (f"LPIPS (AlexNet) {r['held_out_lpips']:.3f} " if r["held_out_lpips"] is not None
                     else "LPIPS not scored (run `manus-capture models install lpips-alex`) ")
                  + f"(train PSNR {r['train_psnr']:.2f} dB); {verdict} the 24 dB goal")


if __name__ == "__main__":
    main()
