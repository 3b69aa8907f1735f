"""MANUS-Hand training speed on crops (takes.crop_views) against whole images.

    .venv/bin/python benchmarks/bench_hand_train.py                  # 640x360 and 1280x720
    .venv/bin/python benchmarks/bench_hand_train.py --steps 30 --config fast --json out.json
    python3 benchmarks/bench_hand_train.py --device cuda             # adds gsplat beside ours

Synthetic data, no simulator: a "true" HandGaussians (60 Gaussians per bone, a random colour per
bone) is posed in `--poses` random poses (hand.random_poses) and rendered into `--cameras` cameras
on a ring around each pose; the masks are alpha > 0.5. The model the builder trains (`--config
surfels`: surfels on the capsule template with builder.surface_hand_config; `--config fast`:
HandConfig.fast's Gaussians around the bones) is trained with train_hand from the same start on
the crops and on the whole images, one after the other in this process, and the steps per second
of each are printed with their ratio. The first step of each run is left out of the rate (it
builds the rasterizer's caches).

With `--device cuda` and gsplat installed, train_hand's rasterizer is gsplat (backend "auto"), and
the rasterizer itself is timed as well: the forward and backward of one training step (render of
one view, L1, backward) with backend="torch" and backend="gsplat", on crops and whole images, with
the ratio and the peak CUDA memory of each (train_hand has no backend argument, so the step is
timed here directly).
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import time
import warnings

import torch

from manus_capture.builder import surface_hand, surface_hand_config
from manus_capture.splat.gaussians import rgb_to_sh0
from manus_capture.splat.hand import HandConfig, HandGaussians, random_poses, train_hand
from manus_capture.splat.rasterize import gsplat_available
from manus_capture.splat.synthetic import look_at
from manus_capture.splat.takes import crop_views
from manus_capture.splat.trainer import SURFACE_EPS2D, Views

# The hand spans about a quarter to a third of the image width, as on the simulated takes' 320x180
# frames (120x80 crops): focal length FOCAL * width at DISTANCE metres from the hand's centre.
FOCAL = 1.0
DISTANCE = 0.6


def true_hand(seed: int) -> HandGaussians:
    """The hand the targets are rendered from: one opaque colour per bone."""
    truth = HandGaussians.initialize(per_bone=60, sh_degree=0, seed=seed)
    colours = torch.rand(20, 3, generator=torch.Generator().manual_seed(seed))
    with torch.no_grad():
        truth.gaussians.params["sh0"][:] = rgb_to_sh0(colours.repeat_interleave(60, 0))[:, None]
        truth.gaussians.params["opacities"][:] = 2.0
    return truth


def synthetic_views(truth: HandGaussians, poses: torch.Tensor, cameras: int, width: int, height: int) -> list[Views]:
    """Per pose, the true hand rendered into `cameras` cameras on a ring around it (elevations
    alternating so that no two views are mirror images), masks alpha > 0.5."""
    f = FOCAL * width
    K = torch.tensor([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]]).repeat(cameras, 1, 1)
    out = []
    for angles in poses:
        centre = truth.skeleton.forward(angles).mean(0)
        eyes = [centre + DISTANCE * torch.tensor([math.cos(2 * math.pi * c / cameras),
                                                  math.sin(2 * math.pi * c / cameras), 0.3 + 0.4 * (c % 2)])
                for c in range(cameras)]
        viewmats = torch.stack([look_at(e, centre) for e in eyes])
        with torch.no_grad():
            images, alpha = truth.render(angles, viewmats, K, width, height, torch.zeros(3))
        out.append(Views(images.clamp(0, 1), K.clone(), viewmats, alpha[..., 0] > 0.5))
    return out


def start_model(config: str, steps: int) -> tuple[HandGaussians, HandConfig]:
    """The model and settings to train: the builder's surfels or HandConfig.fast."""
    if config == "surfels":
        return surface_hand(None), surface_hand_config(steps)
    return HandGaussians.initialize(per_bone=60, sh_degree=1, seed=2), HandConfig.fast(steps)


def sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def train_rate(model: HandGaussians, cfg: HandConfig, poses: torch.Tensor, views: list[Views],
               device: str) -> dict:
    """train_hand on a copy of `model`; steps per second over every step after the first."""
    model = copy.deepcopy(model).to(device)
    views = [v.to(device) for v in views]
    stamps: list[float] = []

    def progress(stage: str, done: int, total: int | None) -> None:
        sync(device)  # a step's time is its kernels' time, not their launch
        stamps.append(time.perf_counter())

    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # LPIPS is off without weights
        history = train_hand(model, poses.to(device), views, cfg, progress=progress)
    # stamps[0] is before step 1, stamps[1] after it: the rate is over steps 2..N
    out = {"steps_per_s": (len(stamps) - 2) / (stamps[-1] - stamps[1]), "first_step_s": stamps[1] - stamps[0],
           "final_loss": history[-1]["loss"]}
    if device == "cuda":
        out["peak_cuda_mb"] = torch.cuda.max_memory_allocated() / 2 ** 20
    return out


def raster_step(model: HandGaussians, angles: torch.Tensor, views: Views, backend: str, eps2d: float,
                repeats: int, device: str) -> dict:
    """Median time and peak CUDA memory of one step's render + L1 + backward, cycling the views."""
    model = copy.deepcopy(model).to(device)
    views = views.to(device)
    angles = angles.to(device)
    bg = torch.zeros(3, device=device)
    times = []
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    for r in range(repeats + 1):
        v = r % len(views)
        sync(device)
        t0 = time.perf_counter()
        rgb, _ = model.render(angles, views.viewmats[v:v + 1], views.Ks[v:v + 1], views.width, views.height, bg,
                              sh_degree=1, backend=backend, eps2d=eps2d)
        (rgb - views.images[v:v + 1]).abs().mean().backward()
        sync(device)
        times.append(time.perf_counter() - t0)
        model.zero_grad(set_to_none=True)
    times = sorted(times[1:])  # the first builds caches (and gsplat's kernels)
    out = {"step_s": times[len(times) // 2]}
    if device == "cuda":
        out["peak_cuda_mb"] = torch.cuda.max_memory_allocated() / 2 ** 20
    return out


def cuda_peak(result: dict) -> str:
    return f", peak CUDA {result['peak_cuda_mb']:.0f} MB" if "peak_cuda_mb" in result else ""


def parse_size(text: str) -> tuple[int, int]:
    w, h = text.lower().split("x")
    return int(w), int(h)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="640x360,1280x720", help="comma-separated WIDTHxHEIGHT")
    parser.add_argument("--steps", type=int, default=20, help="train_hand steps per run (the first is not timed)")
    parser.add_argument("--poses", type=int, default=2)
    parser.add_argument("--cameras", type=int, default=8)
    parser.add_argument("--config", choices=["surfels", "fast"], default="surfels")
    parser.add_argument("--margin", type=int, default=8, help="crop_views margin in pixels")
    parser.add_argument("--repeats", type=int, default=10, help="timed rasterizer steps per backend (CUDA)")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", help="also write the results to this file")
    args = parser.parse_args()
    if args.steps < 3:
        parser.error("--steps must be at least 3 (the first step is not timed)")
    if args.threads:
        torch.set_num_threads(args.threads)
    compare_gsplat = args.device == "cuda" and gsplat_available()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, device {args.device}"
          + (f" ({torch.cuda.get_device_name()})" if args.device == "cuda" else ""))
    if not compare_gsplat:
        print("gsplat: not compared (it needs CUDA and the gsplat package; this run has "
              f"device={args.device}, gsplat {'installed' if gsplat_available() else 'not installed'})")
    elif args.device == "cuda":
        print("train_hand on CUDA rasterizes with gsplat (backend auto); the rasterizer rows compare both")
    truth = true_hand(args.seed + 1)
    poses = random_poses(args.poses, truth.skeleton, torch.Generator().manual_seed(args.seed), rotation=math.pi,
                         translation=0.0)
    model, cfg = start_model(args.config, args.steps)
    eps2d = cfg.eps2d if args.config == "fast" else SURFACE_EPS2D
    print(f"MANUS-Hand {args.config}: {len(model)} Gaussians, {args.poses} poses x {args.cameras} cameras, "
          f"{args.steps} steps per run")
    rows = []
    for size in args.sizes.split(","):
        width, height = parse_size(size)
        whole = synthetic_views(truth, poses, args.cameras, width, height)
        t0 = time.perf_counter()
        crops = [crop_views(v, args.margin) for v in whole]
        crop_s = time.perf_counter() - t0
        row = {"size": f"{width}x{height}", "crop": f"{crops[0].width}x{crops[0].height}", "crop_views_s": crop_s,
               "mask_fraction": float(torch.stack([v.masks.float().mean() for v in whole]).mean()),
               "crops": train_rate(model, cfg, poses, crops, args.device),
               "whole": train_rate(model, cfg, poses, whole, args.device)}
        row["ratio"] = row["crops"]["steps_per_s"] / row["whole"]["steps_per_s"]
        if compare_gsplat:
            for name, views in (("crops", crops), ("whole", whole)):
                for backend in ("torch", "gsplat"):
                    row[f"raster_{name}_{backend}"] = raster_step(model, poses[0], views[0], backend, eps2d,
                                                                  args.repeats, args.device)
        rows.append(row)
        c, w = row["crops"], row["whole"]
        print(f"{row['size']}: crops {row['crop']} ({crops[0].width * crops[0].height / (width * height):.0%} "
              f"of the pixels; hand mask {row['mask_fraction']:.1%} of the frame; crop_views {crop_s:.2f} s)")
        print(f"  train_hand steps/s: crops {c['steps_per_s']:.2f}{cuda_peak(c)}, "
              f"whole {w['steps_per_s']:.2f}{cuda_peak(w)}; "
              f"ratio crops/whole {row['ratio']:.2f}x")
        if compare_gsplat:
            for name in ("crops", "whole"):
                ours, theirs = row[f"raster_{name}_torch"], row[f"raster_{name}_gsplat"]
                print(f"  rasterizer fwd+bwd on {name}: ours {1 / ours['step_s']:.1f} steps/s "
                      f"(peak CUDA {ours['peak_cuda_mb']:.0f} MB), gsplat {1 / theirs['step_s']:.1f} steps/s "
                      f"({theirs['peak_cuda_mb']:.0f} MB); ours/gsplat time {ours['step_s'] / theirs['step_s']:.1f}x")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"torch": torch.__version__, "threads": torch.get_num_threads(), "device": args.device,
                       "config": args.config, "gaussians": len(model), "steps": args.steps, "poses": args.poses,
                       "cameras": args.cameras, "rows": rows}, fh, indent=1)


if __name__ == "__main__":
    main()
