"""`manus-capture reconstruct`: Gaussian models of the object (and, later, the hand).

    manus-capture reconstruct object --cameras CALIB/cameras.json --take TAKE [--frame K] \\
        [--masks DIR] [--test-cameras a,b] -o object.safetensors
    manus-capture reconstruct object --cameras cameras.json --images DIR [--masks DIR] -o object.safetensors
    manus-capture reconstruct render object.safetensors --cameras cameras.json -o DIR

Images come from one frame of a take (every camera's frame index K) or from a folder with one
image per camera, named by camera id (CAM.png or CAM.jpg); masks from a folder of CAM.png
(non-zero = object). Images and masks are undistorted with the calibration and may be reduced
(--scale) before training. See docs/splat.md.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import click
import numpy as np

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


class ReconstructInputError(ValueError):
    """Bad input to reconstruct: names the file and the problem (exit code 2)."""

    exit_code = 2


def _colour(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(0 <= v <= 1 for v in values):
        raise click.BadParameter(f"{text!r}: expected three numbers in [0,1], e.g. 1,1,1")
    return values


def _read_image(folder: Path, cam: str, flags: int) -> np.ndarray:
    import cv2

    for suffix in IMAGE_SUFFIXES:
        path = folder / f"{cam}{suffix}"
        if path.exists():
            image = cv2.imread(str(path), flags)
            if image is None:
                raise ReconstructInputError(f"{path}: not a readable image")
            return image
    raise ReconstructInputError(f"{folder}: no image for camera {cam!r} ({cam}.png or {cam}.jpg)")


def _prepare(rig, images: list[np.ndarray], masks: list[np.ndarray] | None, scale: float):
    """Undistort and reduce: (images (V,H,W,3) float RGB in [0,1], masks (V,H,W) bool | None, K (V,3,3))."""
    import cv2

    out_images, out_masks, Ks = [], [], []
    for i, image in enumerate(images):
        K, dist = rig.K[i], rig.dist[i]
        w, h = int(rig.size[i, 0]), int(rig.size[i, 1])
        if image.shape[:2] != (h, w):
            raise ReconstructInputError(f"camera {rig.ids[i]}: image is {image.shape[1]}x{image.shape[0]}, "
                                        f"the calibration says {w}x{h}")
        size = (max(int(round(w * scale)), 1), max(int(round(h * scale)), 1))
        sx, sy = size[0] / w, size[1] / h
        # Pixel centres at integer coordinates: x' = (x + 0.5) s - 0.5.
        K_new = np.array([[K[0, 0] * sx, K[0, 1] * sx, (K[0, 2] + 0.5) * sx - 0.5],
                          [0, K[1, 1] * sy, (K[1, 2] + 0.5) * sy - 0.5], [0, 0, 1]])
        undistorted = cv2.undistort(image, K, dist)
        out_images.append(cv2.resize(undistorted, size, interpolation=cv2.INTER_AREA)[..., ::-1] / 255.0)
        if masks is not None:
            m = cv2.undistort((masks[i] > 0).astype(np.float32), K, dist)
            out_masks.append(cv2.resize(m, size, interpolation=cv2.INTER_AREA) > 0.5)
        Ks.append(K_new)
    sizes = {im.shape[:2] for im in out_images}
    if len(sizes) != 1:
        raise ReconstructInputError(f"the cameras' image sizes differ after --scale ({sorted(sizes)}); "
                                    "train cameras of one resolution together")
    return (np.stack(out_images).astype(np.float32), None if masks is None else np.stack(out_masks),
            np.stack(Ks))


@click.group("reconstruct", context_settings={"help_option_names": ["-h", "--help"]})
def command() -> None:
    """Train Gaussian models of the object (and render them)."""


@command.command("object")
@click.option("--cameras", "cameras_path", type=click.Path(path_type=Path), required=True,
              help="The calibration (cameras.json or any format load_cameras reads).")
@click.option("--take", type=click.Path(path_type=Path), default=None, help="Object take: images from its videos.")
@click.option("--frame", type=click.IntRange(0), default=0, show_default=True, help="Frame index in the take.")
@click.option("--images", "images_dir", type=click.Path(path_type=Path), default=None,
              help="Folder with one image per camera (CAM.png / CAM.jpg), instead of --take.")
@click.option("--masks", "masks_dir", type=click.Path(path_type=Path), default=None,
              help="Folder with one object mask per camera (CAM.png, non-zero = object).")
@click.option("--test-cameras", default="", help="Comma-separated camera ids held out for evaluation.")
@click.option("--scale", type=click.FloatRange(0.01, 1.0), default=0.25, show_default=True,
              help="Image scale for training.")
@click.option("--iterations", type=click.IntRange(1), default=7000, show_default=True)
@click.option("--sh-degree", type=click.IntRange(0, 3), default=3, show_default=True)
@click.option("--points", type=click.IntRange(1), default=20_000, show_default=True,
              help="Initial Gaussians in the visual hull.")
@click.option("--background", default="0,0,0", show_default=True, help="Background colour r,g,b in [0,1].")
@click.option("--lpips-weights", type=click.Path(path_type=Path, exists=True), default=None,
              help="LPIPS state dict (see docs/splat.md); LPIPS is off without it.")
@click.option("--lpips-net", type=click.Choice(["alex", "vgg"]), default="alex", show_default=True)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True, help="Checkpoint (.safetensors).")
@click.option("--force", is_flag=True, help="Overwrite an existing checkpoint.")
def object_command(cameras_path: Path, take: Path | None, frame: int, images_dir: Path | None,
                   masks_dir: Path | None, test_cameras: str, scale: float, iterations: int, sh_degree: int,
                   points: int, background: str, lpips_weights: Path | None, lpips_net: str, seed: int,
                   output: Path, force: bool) -> None:
    """Fit static Gaussians to the calibrated views of an object; print held-out PSNR/SSIM."""
    import cv2

    from dataset_tools.calibration.formats import load_cameras
    from manus_capture.splat.checkpoint import save_checkpoint
    from manus_capture.splat.losses import load_lpips
    from manus_capture.splat.trainer import ObjectConfig, Views, evaluate, train_object

    if (take is None) == (images_dir is None):
        raise click.UsageError("give exactly one of --take and --images")
    if output.exists() and not force:
        raise ReconstructInputError(f"{output}: exists (use --force to overwrite)")
    bg = _colour(background)
    rig = load_cameras(cameras_path)
    held_out = [c.strip() for c in test_cameras.split(",") if c.strip()]
    for cam in held_out:
        rig.index(cam)  # KeyError names an unknown camera
    if take is not None:
        from dataset_tools.take import Take

        tk = Take(take)
        missing = [c for c in rig.ids if c not in tk.cameras]
        if missing:
            raise ReconstructInputError(f"{take}: no videos of calibrated cameras {', '.join(missing)}")
        raw = [tk.read_frame(cam, frame) for cam in rig.ids]
    else:
        raw = [_read_image(images_dir, cam, cv2.IMREAD_COLOR) for cam in rig.ids]
    raw_masks = None if masks_dir is None else [_read_image(masks_dir, c, cv2.IMREAD_GRAYSCALE) for c in rig.ids]
    images, masks, Ks = _prepare(rig, raw, raw_masks, scale)
    views = Views.from_rig(images, Ks, rig.R, rig.t, masks)
    test_idx = [rig.index(c) for c in held_out]
    train_idx = [i for i in range(len(rig)) if i not in test_idx]
    if not train_idx:
        raise click.UsageError("--test-cameras holds out every camera")

    cfg = ObjectConfig(iterations=iterations, sh_degree=sh_degree, init_points=points, background=bg,
                       lpips_weights=None if lpips_weights is None else str(lpips_weights), lpips_net=lpips_net,
                       seed=seed)
    start = time.perf_counter()
    result = train_object(views.subset(train_idx), cfg)
    elapsed = time.perf_counter() - start
    save_checkpoint(output, result.gaussians, kind="object",
                    metadata={"calibration": str(cameras_path), "source": str(take or images_dir),
                              "frame": str(frame), "scale": str(scale), "background": background,
                              "test_cameras": ",".join(held_out)})
    summary = f"{output}: {len(result.gaussians)} Gaussians from {len(train_idx)} views, {elapsed:.0f} s"
    if test_idx:
        lpips = None if lpips_weights is None else load_lpips(lpips_weights, lpips_net)
        scores = evaluate(result.gaussians, views.subset(test_idx), bg, lpips)
        summary += f"; held-out PSNR {scores['psnr']:.2f} dB, SSIM {scores['ssim']:.3f}"
        if "lpips" in scores:
            summary += f", LPIPS {scores['lpips']:.3f}"
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
    import cv2
    import torch
    from tqdm import tqdm

    from dataset_tools.calibration.formats import load_cameras
    from dataset_tools.fileio import write_atomic
    from manus_capture.splat.checkpoint import load_checkpoint
    from manus_capture.splat.hand import HandGaussians
    from manus_capture.splat.trainer import render

    rig = load_cameras(cameras_path)
    gaussians, extra, meta = load_checkpoint(checkpoint)
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
    for i in tqdm(range(len(rig)), desc="render", unit="view", file=sys.stderr):
        path = output / f"{rig.ids[i]}.png"
        if path.exists() and not force:
            raise ReconstructInputError(f"{path}: exists (use --force to overwrite)")
        w, h = int(round(rig.size[i, 0] * scale)), int(round(rig.size[i, 1] * scale))
        K = torch.tensor(rig.K[i], dtype=torch.float32)
        K[:2] *= scale
        K[:2, 2] += 0.5 * scale - 0.5
        V = torch.eye(4)
        V[:3, :3], V[:3, 3] = torch.tensor(rig.R[i]), torch.tensor(rig.t[i])
        with torch.no_grad():
            if hand is None:
                rgb, _ = render(gaussians, V[None], K[None], w, h, bg)
            else:
                rgb, _ = hand.render(pose, V[None], K[None], w, h, bg)
        image = (rgb[0].clamp(0, 1).numpy()[..., ::-1] * 255 + 0.5).astype(np.uint8)
        write_atomic(path, cv2.imencode(".png", image)[1].tobytes())
    click.echo(f"{output}: {len(rig)} views of {checkpoint.name} ({meta.get('kind')}, {len(gaussians)} Gaussians), "
               f"{time.perf_counter() - start:.1f} s")
