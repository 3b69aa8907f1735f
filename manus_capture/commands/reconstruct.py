"""`manus-capture reconstruct`: Gaussian models of the object and of the hand (MANUS-Hand).

    manus-capture reconstruct object --cameras CALIB/cameras.json --take TAKE [--frame K] \\
        [--masks truth|DIR] [--test-cameras a,b] -o object.safetensors
    manus-capture reconstruct object --cameras cameras.json --images DIR [--masks DIR] -o object.safetensors
    manus-capture reconstruct hand --cameras cameras.json --take HAND_TAKE (--dataset DATASET.h5 | --truth) \\
        [--frames 0,12,24] [--test-frames 36] -o hand.safetensors
    manus-capture reconstruct render model.safetensors --cameras cameras.json -o DIR

The command is a thin layer over manus_capture.splat.takes (views from takes) and the trainers;
see docs/splat.md.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import click
import cv2
import numpy as np
import torch

from dataset_tools.calibration.formats import load_cameras
from manus_capture.bars import Bars
from manus_capture.builder import surface_hand, surface_hand_config
from manus_capture.splat.checkpoint import load_checkpoint, save_checkpoint
from manus_capture.splat.hand import HandConfig, HandGaussians, evaluate_hand
from manus_capture.splat.losses import metric_lpips
from manus_capture.splat.rasterize import EPS2D
from manus_capture.splat.takes import (
    crop_views,
    empty_scene,
    hand_frames_from_dataset,
    hand_frames_from_truth,
    hand_masks_from_dataset,
    hand_views_from_take,
    mask_cameras,
    object_views_from_take,
    spread_frames,
    still_frames,
    undistort,
)
from manus_capture.splat.trainer import ObjectConfig, Views, evaluate, render, world_to_camera
from manus_capture.torch_threads import TRAIN_THREADS
from manus_capture.train_tasks import HandTraining, ObjectTraining, train_in_task
from manus_core.cameras import scale_intrinsics
from manus_core.errors import ReconstructInputError
from manus_core.fileio import write_atomic
from manus_core.take import Take

from .cluster import cluster_options

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def _colour(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(0 <= v <= 1 for v in values):
        raise click.BadParameter(f"{text!r}: expected three numbers in [0,1], e.g. 1,1,1")
    return values


def _read_image(folder: Path, cam: str, flags: int) -> np.ndarray:
    for suffix in IMAGE_SUFFIXES:
        path = folder / f"{cam}{suffix}"
        if path.exists():
            image = cv2.imread(str(path), flags)
            if image is None:
                raise ReconstructInputError(f"{path}: not a readable image")
            return image
    raise ReconstructInputError(f"{folder}: no image for camera {cam!r} ({cam}.png or {cam}.jpg)")


def _id_list(text: str) -> list[str]:
    return [c.strip() for c in text.split(",") if c.strip()]


def _int_list(text: str, option: str) -> list[int]:
    try:
        return [int(v) for v in _id_list(text)]
    except ValueError:
        raise click.BadParameter(f"{text!r}: expected comma-separated frame numbers", param_hint=option) from None


def _load_rig(cameras_path: Path, only: str, take: Path | None = None):
    """The calibration, restricted to --only-cameras when given (KeyError names an unknown id).
    The cameras of `take` that it lacks (a partial calibration) are named in one line; fewer than
    two cameras left is refused then."""
    rig = load_cameras(cameras_path)
    uncalibrated = [] if take is None else [c for c in Take(take).cameras if c not in rig.ids]
    if uncalibrated:
        click.echo(f"note: cameras {', '.join(uncalibrated)} of {take} are not in the calibration: left out", err=True)
    ids = _id_list(only)
    return _at_least_two(rig.subset(ids) if ids else rig, take, bool(uncalibrated))


def _at_least_two(rig, take: Path | None, left_out: bool):
    if left_out and len(rig) < 2:
        raise ReconstructInputError(f"{take}: {len(rig)} cameras left ({', '.join(rig.ids) or 'none'}); "
                                    "training needs at least 2")
    return rig


def _with_results(rig, take: Path, *having: tuple[str, list[str]]):
    """The rig without the cameras that lack `having`'s results ((what, cameras) each, e.g. the
    annotation's cameras), named in one line each."""
    lacking = []
    for what, cameras in having:
        missing = [c for c in rig.ids if c not in cameras]
        if missing:
            click.echo(f"note: cameras {', '.join(missing)} have no {what}: left out", err=True)
            lacking += missing
    return _at_least_two(rig.subset([c for c in rig.ids if c not in lacking]), take, bool(lacking))


def _check_output(output: Path, force: bool) -> None:
    if output.exists() and not force:
        raise ReconstructInputError(f"{output}: exists (use --force to overwrite)")


def _with_lpips_loss(cfg, weight: float):
    """A training config with `weight` for LPIPS in its loss (the short CPU configs have none)."""
    return dataclasses.replace(cfg, weights=dataclasses.replace(cfg.weights, lpips=weight))


def _scores_text(scores: dict[str, float]) -> str:
    text = f"held-out PSNR {scores['psnr']:.2f} dB, SSIM {scores['ssim']:.3f}"
    if "psnr_mask" in scores:
        text += f", PSNR on the mask {scores['psnr_mask']:.2f} dB"
    if "lpips" in scores:
        text += f", LPIPS {scores['lpips']:.3f}"
    return text


@click.group("reconstruct", context_settings={"help_option_names": ["-h", "--help"]})
def command() -> None:
    """Train Gaussian models of the object and of the hand (and render them)."""


def _empty_scene(empty: Path | None, cameras: list[str]) -> dict[str, np.ndarray] | None:
    """--empty's scene per camera, or None without it."""
    return None if empty is None else empty_scene(empty, cameras)


def _common_options(f):
    """Options shared by `object` and `hand`."""
    options = [
        click.option("--cameras", "cameras_path", type=click.Path(path_type=Path), required=True,
                     help="The calibration (cameras.json or any format load_cameras reads)."),
        click.option("--only-cameras", default="", help="Comma-separated camera ids to use (default: all)."),
        click.option("--scale", type=click.FloatRange(0.01, 1.0), default=0.25, show_default=True,
                     help="Image scale for training."),
        click.option("--crop-margin", type=click.IntRange(0), default=8, show_default=True,
                     help="Train on windows this many pixels around the masks (views with masks)."),
        click.option("--sh-degree", type=click.IntRange(0, 3), default=1, show_default=True),
        click.option("--background", default="0,0,0", show_default=True, help="Background colour r,g,b in [0,1]."),
        click.option("--empty", "empty", type=click.Path(path_type=Path, exists=True, file_okay=False), default=None,
                     help="A take of the empty cube (segment's --background): renders are put over what each "
                          "camera sees of it, as the cameras see the subject, instead of over --background."),
        click.option("--lpips-weights", type=click.Path(path_type=Path, exists=True), default=None,
                     help="LPIPS state dict (see docs/splat.md); default: the one `manus-capture models install "
                          "lpips-alex` (or lpips-vgg) installed. With either, the held-out views get LPIPS too."),
        click.option("--lpips-loss", type=click.FloatRange(0), default=0.0, show_default=True,
                     help="Weight of LPIPS in the training loss (the MANUS paper's: 0.1; 0 in these short CPU "
                          "settings, where it slowed training by a quarter and gained nothing: docs/splat.md)."),
        click.option("--lpips-net", type=click.Choice(["alex", "vgg"]), default="alex", show_default=True),
        click.option("--seed", type=int, default=0, show_default=True),
        click.option("--threads", type=click.IntRange(1), default=TRAIN_THREADS,
                     help="Torch threads of the training (default: this machine's cores): the checkpoint depends "
                          "on it, not on where it ran."),
        click.option("-o", "--output", type=click.Path(path_type=Path), required=True,
                     help="Checkpoint (.safetensors)."),
        click.option("--force", is_flag=True, help="Overwrite an existing checkpoint."),
    ]
    for option in reversed(options):
        f = option(f)
    return cluster_options("into one task: the model, trained in one process or on one Dask worker")(f)


@command.command("object")
@click.option("--take", type=click.Path(path_type=Path), default=None, help="Object take: images from its videos.")
@click.option("--frame", type=click.IntRange(0), default=None,
              help="Frame index in the take (default: the first labelled tick with --masks truth, else 0).")
@click.option("--images", "images_dir", type=click.Path(path_type=Path), default=None,
              help="Folder with one image per camera (CAM.png / CAM.jpg), instead of --take.")
@click.option("--masks", "masks_arg", default=None,
              help="'truth' (labels of a simulated take's ground_truth.h5) or a folder with one object mask "
                   "per camera (CAM.png, non-zero = object).")
@click.option("--test-cameras", default="", help="Comma-separated camera ids held out for evaluation.")
@click.option("--iterations", type=click.IntRange(1), default=1000, show_default=True)
@click.option("--points", type=click.IntRange(1), default=3000, show_default=True,
              help="Initial Gaussians in the visual hull.")
@click.option("--surfels/--no-surfels", default=True, show_default=True,
              help="With masks: flat Gaussians on the visual hull's surface, at most 2 mm wide, whose centres "
                   "stay on the object's surface (what `contacts` measures between); --no-surfels fills the "
                   "hull with round Gaussians of any size (semi-transparent or large scenes).")
@_common_options
def object_command(take: Path | None, frame: int | None, images_dir: Path | None, masks_arg: str | None,
                   test_cameras: str, iterations: int, points: int, surfels: bool, cameras_path: Path,
                   only_cameras: str, scale: float, crop_margin: int, sh_degree: int, background: str,
                   empty: Path | None, lpips_weights: Path | None, lpips_loss: float, lpips_net: str, seed: int,
                   threads: int, output: Path, force: bool, workers: int, scheduler: str | None) -> None:
    """Fit static Gaussians to the calibrated views of an object; print held-out PSNR/SSIM."""
    if (take is None) == (images_dir is None):
        raise click.UsageError("give exactly one of --take and --images")
    if empty is not None and take is None:
        raise click.UsageError("--empty needs --take (the empty take's frames stand behind the take's)")
    if masks_arg == "truth" and take is None:
        raise click.UsageError("--masks truth needs --take (a simulated take with ground_truth.h5)")
    _check_output(output, force)
    bg = _colour(background)
    rig = _load_rig(cameras_path, only_cameras, take)
    held_out = _id_list(test_cameras)
    for cam in held_out:
        rig.index(cam)  # KeyError names an unknown camera
    masks = None
    if masks_arg is not None and masks_arg != "truth":
        masks = np.stack([_read_image(Path(masks_arg), c, cv2.IMREAD_GRAYSCALE) > 0 for c in rig.ids])
    if take is not None:
        views = object_views_from_take(take, rig, frame, masks_arg if masks_arg == "truth" else masks, scale,
                                       behind=_empty_scene(empty, rig.ids))
    else:
        images = [_read_image(images_dir, cam, cv2.IMREAD_COLOR) for cam in rig.ids]
        imgs, msk, Ks = undistort(rig, images, masks, scale)
        views = Views.from_rig(imgs, Ks, rig.R, rig.t, msk, rig.ids)
    test_idx = [i for i, c in enumerate(views.ids) if c in held_out]
    train_idx = [i for i in range(len(views)) if i not in test_idx]
    if not train_idx:
        raise click.UsageError("--test-cameras holds out every camera")

    # surfels need masks to find the surface
    make_config = ObjectConfig.surfels if surfels and views.masks is not None else ObjectConfig.fast
    cfg = _with_lpips_loss(make_config(iterations, sh_degree=sh_degree, init_points=points, background=bg,
                                       lpips_weights=None if lpips_weights is None else str(lpips_weights),
                                       lpips_net=lpips_net, seed=seed), lpips_loss)
    start = time.perf_counter()
    task = ObjectTraining(crop_views(views.subset(train_idx), crop_margin), cfg, threads)
    with Bars() as bars:
        gaussians = train_in_task(task, f"object-{output.resolve()}", workers, scheduler, bars)
    elapsed = time.perf_counter() - start
    save_checkpoint(output, gaussians, kind="object",
                    metadata={"calibration": str(cameras_path), "source": str(take or images_dir),
                              "frame": str(frame), "scale": str(scale), "background": background,
                              "empty": str(empty or ""), "cameras": ",".join(views.ids),
                              "test_cameras": ",".join(held_out), "eps2d": str(cfg.eps2d)})
    summary = f"{output}: {len(gaussians)} Gaussians from {len(train_idx)} views, {elapsed:.0f} s"
    if test_idx:
        summary += "; " + _scores_text(evaluate(gaussians, views.subset(test_idx), bg,
                                                metric_lpips(lpips_weights, lpips_net), cfg.eps2d))
    click.echo(summary)


@command.command("hand")
@click.option("--take", type=click.Path(path_type=Path), required=True, help="The subject's hand take.")
@click.option("--dataset", "dataset_path", type=click.Path(path_type=Path), default=None,
              help="DATASET.h5 from annotate: each frame's own IK fit (joint_angles_raw), bone lengths "
                   "and frame groups of the take.")
@click.option("--dataset-take", default=None, help="SESSION/TAKE key in --dataset (default: its only take).")
@click.option("--truth", is_flag=True, help="Joint angles and bone lengths from the take's ground_truth.h5 "
                                            "(simulated takes) instead of --dataset.")
@click.option("--frames", "frames_arg", default="",
              help="Comma-separated frames (dataset rows, or ticks with --truth) to train on "
                   "(default: the middle of every hold, see --poses).")
@click.option("--poses", type=click.IntRange(1), default=20, show_default=True,
              help="Without --frames: this many holds, spread over the take.")
@click.option("--test-frames", default="",
              help="Comma-separated frames held out for evaluation (default: every fifth chosen frame).")
@click.option("--masks", "masks_arg", type=click.Choice(["dataset", "truth"]), default=None,
              help="Hand masks: those `segment` stored in --dataset for the take (default with --dataset), "
                   "or the labels of a simulated take's ground_truth.h5 (default with --truth).")
@click.option("--iterations", type=click.IntRange(1), default=1000, show_default=True)
@click.option("--init", "init", type=click.Choice(["surface", "bones"]), default="surface", show_default=True,
              help="surface: surfels on the capsule template, whose centres stay on the hand's surface "
                   "(what `contacts` measures between); bones: round Gaussians around every bone.")
@click.option("--per-bone", type=click.IntRange(1), default=60, show_default=True,
              help="With --init bones: initial Gaussians around each of the 20 bones.")
@_common_options
def hand_command(take: Path, dataset_path: Path | None, dataset_take: str | None, truth: bool, frames_arg: str,
                 poses: int, test_frames: str, masks_arg: str | None, iterations: int, init: str, per_bone: int,
                 cameras_path: Path, only_cameras: str, scale: float, crop_margin: int, sh_degree: int,
                 background: str, empty: Path | None, lpips_weights: Path | None, lpips_loss: float, lpips_net: str,
                 seed: int, threads: int, output: Path, force: bool, workers: int, scheduler: str | None) -> None:
    """Fit a MANUS-Hand model (articulated Gaussians) to a hand take; print held-out PSNR/SSIM."""
    if truth == (dataset_path is not None):
        raise click.UsageError("give exactly one of --dataset and --truth")
    _check_output(output, force)
    bg = _colour(background)
    hand = hand_frames_from_truth(take) if truth else hand_frames_from_dataset(dataset_path, dataset_take)
    masks_arg = masks_arg or ("truth" if truth else "dataset")
    having = [(f"annotation in {hand.source}", list(hand.cameras))]
    if masks_arg == "dataset":
        if dataset_path is None:
            raise click.UsageError("--masks dataset needs --dataset")
        having.append((f"masks in {dataset_path}", mask_cameras(dataset_path, hand.key)))
    rig = _with_results(_load_rig(cameras_path, only_cameras, take), take, *having)
    frames = _int_list(frames_arg, "--frames") or [int(f) for f in still_frames(hand.angles, count=poses)]
    if not frames:
        frames = [int(f) for f in spread_frames(hand.angles, poses)]
        if len(frames) < 2:
            raise ReconstructInputError(f"{hand.source}: fewer than two frames with a fitted hand")
        click.echo(f"no holds in {hand.source}: {len(frames)} frame groups spread over the take", err=True)
    test = _int_list(test_frames, "--test-frames") or frames[2::5]
    frames = list(dict.fromkeys(frames + test))
    train_rows = [i for i, f in enumerate(frames) if f not in test]
    if not train_rows:
        raise click.UsageError("--test-frames holds out every frame")
    if masks_arg == "dataset":
        masks = hand_masks_from_dataset(dataset_path, hand.key, frames, rig.ids)
    else:
        masks = "truth"
    angles, views = hand_views_from_take(take, rig, hand, frames, masks, scale, behind=_empty_scene(empty, rig.ids))

    settings = dict(sh_degree=sh_degree, background=bg, seed=seed,
                    lpips_weights=None if lpips_weights is None else str(lpips_weights), lpips_net=lpips_net)
    if init == "surface":
        model, cfg = surface_hand(hand.bone_lengths, sh_degree), surface_hand_config(iterations, **settings)
    else:
        model = HandGaussians.initialize(hand.bone_lengths, per_bone=per_bone, sh_degree=sh_degree, seed=seed)
        cfg = HandConfig.fast(iterations, **settings)
    cfg = _with_lpips_loss(cfg, lpips_loss)
    start = time.perf_counter()
    task = HandTraining(model, angles[train_rows], [crop_views(views[i], crop_margin) for i in train_rows], cfg,
                        threads)
    with Bars() as bars:
        model = train_in_task(task, f"hand-{output.resolve()}", workers, scheduler, bars)
    elapsed = time.perf_counter() - start
    save_checkpoint(output, model.gaussians, kind="hand", extra=model.extra_tensors(),
                    metadata={"calibration": str(cameras_path), "source": str(take), "angles": hand.source,
                              "frames": ",".join(map(str, frames)), "test_frames": ",".join(map(str, test)),
                              "scale": str(scale), "background": background, "empty": str(empty or ""),
                              "eps2d": str(cfg.eps2d)})
    n_views = sum(len(views[i]) for i in train_rows)
    n_poses = sum(1 for i in train_rows if len(views[i]))
    summary = f"{output}: {len(model)} Gaussians from {n_poses} poses ({n_views} views), {elapsed:.0f} s"
    test_rows = [i for i in range(len(frames)) if i not in train_rows]
    if test_rows:
        scores = evaluate_hand(model, angles[test_rows], [views[i] for i in test_rows], bg, cfg.eps2d,
                               metric_lpips(lpips_weights, lpips_net))
        summary += f"; {len(test_rows)} held-out poses: " + (
            _scores_text(scores) if scores else "no view of them to score (none with the hand in its mask)")
    click.echo(summary)


@command.command("render")
@click.argument("checkpoint", type=click.Path(path_type=Path, exists=True, dir_okay=False))
@click.option("--cameras", "cameras_path", type=click.Path(path_type=Path), required=True,
              help="Cameras to render (cameras.json or any format load_cameras reads).")
@click.option("--scale", type=click.FloatRange(0.01, 4.0), default=1.0, show_default=True)
@click.option("--background", default="0,0,0", show_default=True, help="Background colour r,g,b in [0,1].")
@click.option("--angles", default=None,
              help="Hand checkpoints: 26 comma-separated joint angles (default: the rest pose).")
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True, help="Folder for CAM.png.")
@click.option("--force", is_flag=True, help="Overwrite existing images.")
def render_command(checkpoint: Path, cameras_path: Path, scale: float, background: str, angles: str | None,
                   output: Path, force: bool) -> None:
    """Render a checkpoint into every camera of a calibration (undistorted pinhole images)."""
    rig = load_cameras(cameras_path)
    gaussians, extra, meta = load_checkpoint(checkpoint)
    eps2d = float(meta.get("eps2d", EPS2D))  # the splat blur the model was trained with
    hand = HandGaussians.from_checkpoint(gaussians, extra) if meta.get("kind") == "hand" else None
    pose = torch.zeros(26)
    if angles is not None:
        try:
            pose = torch.tensor([float(a) for a in angles.split(",")])
        except ValueError:
            pose = torch.zeros(0)
        if pose.shape != (26,):
            raise click.BadParameter("expected 26 comma-separated numbers", param_hint="--angles")
    bg = torch.tensor(_colour(background))
    start = time.perf_counter()
    with Bars(unit="view") as bars:
        bars("render", 0, len(rig))
        for i in range(len(rig)):
            path = output / f"{rig.ids[i]}.png"
            if path.exists() and not force:
                raise ReconstructInputError(f"{path}: exists (use --force to overwrite)")
            w, h = int(round(rig.size[i, 0] * scale)), int(round(rig.size[i, 1] * scale))
            K = torch.tensor(scale_intrinsics(rig.K[i], scale), dtype=torch.float32)
            V = world_to_camera(rig.R[i:i + 1], rig.t[i:i + 1])[0]
            with torch.no_grad():
                if hand is None:
                    rgb, _ = render(gaussians, V[None], K[None], w, h, bg, eps2d=eps2d)
                else:
                    rgb, _ = hand.render(pose, V[None], K[None], w, h, bg, eps2d=eps2d)
            image = (rgb[0].clamp(0, 1).numpy()[..., ::-1] * 255 + 0.5).astype(np.uint8)
            write_atomic(path, cv2.imencode(".png", image)[1].tobytes())
            bars("render", i + 1, len(rig))
    click.echo(f"{output}: {len(rig)} views of {checkpoint.name} ({meta.get('kind')}, {len(gaussians)} Gaussians), "
               f"{time.perf_counter() - start:.1f} s")
