"""JPEG encoding of raw 1280x720 frames: what a recorder of GigE cameras (Mono8/Bayer pixels) pays.

    .venv/bin/python benchmarks/bench_jpeg.py [--frames N] [--quality Q]

Frames: 1280x720 scenes like the cube's (multi-scale colour texture, black-and-white squares as
tags, sensor noise sigma 2), made here so that the script needs nothing but numpy and OpenCV.
Each is also mosaicked to a BayerBG8 frame, what a colour GigE camera hands out.

Encoders, each on one thread (frames per second per core):
  opencv     cv2.imencode (libjpeg-turbo in OpenCV's wheels), BGR 4:2:0
  pillow     PIL.Image.save(format="JPEG") (libjpeg-turbo in Pillow's wheels), RGB 4:2:0
  bayer+cv2  demosaic (cv2.cvtColor BayerBG2BGR) then cv2.imencode: the whole cost per raw frame
  nvjpeg     torchvision.io.encode_jpeg on CUDA tensors, frames in batches (only with a CUDA GPU and
             torchvision; the upload of the frames is timed with it)
The 53-camera cube at 120 FPS makes 6360 frames/s: the table gives the cores (or GPUs) that takes.
"""

from __future__ import annotations

import argparse
import io
import time

import cv2
import numpy as np

CUBE_FPS = 53 * 120


def scenes(n: int, width: int = 1280, height: int = 720, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        img = np.zeros((height, width, 3), np.float32)
        for cells in (6, 17, 45, 120):
            field = rng.random((cells * height // width + 1, cells, 3), dtype=np.float32)
            img += cv2.resize(field, (width, height), interpolation=cv2.INTER_CUBIC) / cells ** 0.3
        img = 60 + 140 * (img - img.min()) / (img.max() - img.min())
        for _ in range(40):   # tags: dark squares in light quiet zones
            s = int(rng.integers(20, 90))
            x, y = int(rng.integers(0, width - s)), int(rng.integers(0, height - s))
            img[y:y + s, x:x + s] = 235
            cells = (rng.random((8, 8)) > 0.5) * 215 + 20
            img[y + s // 8:y + s - s // 8, x + s // 8:x + s - s // 8] = cv2.resize(
                cells.astype(np.float32), (s - 2 * (s // 8),) * 2, interpolation=cv2.INTER_NEAREST)[..., None]
        img += rng.normal(0, 2, img.shape)
        out.append(np.clip(img, 0, 255).astype(np.uint8))
    return out


def bayer(bgr: np.ndarray) -> np.ndarray:
    """BayerBG8 mosaic of a BGR frame (B at even rows and columns), as such a camera's raw buffer."""
    raw = np.empty(bgr.shape[:2], np.uint8)
    raw[0::2, 0::2] = bgr[0::2, 0::2, 0]
    raw[0::2, 1::2] = bgr[0::2, 1::2, 1]
    raw[1::2, 0::2] = bgr[1::2, 0::2, 1]
    raw[1::2, 1::2] = bgr[1::2, 1::2, 2]
    return raw


def rate(encode, frames: list, seconds: float = 2.0) -> tuple[float, int]:
    """(frames per second, mean bytes per frame) of encode over frames, repeated for `seconds`."""
    encode(frames[0])   # warm-up
    n, size, start = 0, 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        for f in frames:
            size += encode(f)
            n += 1
    return n / (time.perf_counter() - start), size // n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--quality", type=int, default=90)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    frames = scenes(args.frames)
    raws = [bayer(f) for f in frames]
    q = args.quality
    params = [cv2.IMWRITE_JPEG_QUALITY, q, cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420]

    def opencv(f):
        return len(cv2.imencode(".jpg", f, params)[1])

    def pillow(f):
        from PIL import Image

        buf = io.BytesIO()
        Image.fromarray(f[..., ::-1]).save(buf, format="JPEG", quality=q, subsampling=2)
        return buf.tell()

    def bayer_opencv(r):
        return len(cv2.imencode(".jpg", cv2.cvtColor(r, cv2.COLOR_BayerBG2BGR), params)[1])

    rows = [("opencv", *rate(opencv, frames)), ("pillow", *rate(pillow, frames)),
            ("bayer+cv2", *rate(bayer_opencv, raws))]
    gpu = _nvjpeg(frames, q)
    print(f"1280x720 frames, quality {q}, 4:2:0; one thread per CPU encoder\n")
    print("| encoder | frames/s | KB/frame | cores for 53 x 120 FPS |")
    print("|---|---|---|---|")
    for name, fps, size in rows:
        print(f"| {name} | {fps:.0f} | {size / 1e3:.0f} | {CUBE_FPS / fps:.1f} |")
    if isinstance(gpu, str):
        print(f"\nnvjpeg: {gpu}")
    else:
        name, fps, size = gpu
        print(f"| {name} | {fps:.0f} | {size / 1e3:.0f} | {CUBE_FPS / fps:.2f} GPUs |")
    best = max(rows[:2], key=lambda r: r[1])
    print(f"\nfastest CPU encoder: {best[0]}; pillow / opencv {rows[1][1] / rows[0][1]:.2f}; "
          f"demosaic + encode / encode {rows[2][1] / rows[0][1]:.2f}")


def _nvjpeg(frames: list[np.ndarray], quality: int) -> tuple[str, float, int] | str:
    """nvJPEG through torchvision on the GPU, batches of 16 frames, or why it was not measured."""
    try:
        import torch
        from torchvision.io import encode_jpeg
    except ImportError as exc:
        return f"not measured ({exc.name} is not installed)"
    if not torch.cuda.is_available():
        return "not measured (no CUDA GPU)"
    batch = [torch.from_numpy(np.ascontiguousarray(f[..., ::-1].transpose(2, 0, 1))) for f in frames]
    batch = (batch * (16 // len(batch) + 1))[:16]

    def encode(chunk):
        out = encode_jpeg([t.cuda(non_blocking=True) for t in chunk], quality=quality)
        torch.cuda.synchronize()
        return sum(len(o) for o in out)

    encode(batch)
    n, size, start = 0, 0, time.perf_counter()
    while time.perf_counter() - start < 2.0:
        size += encode(batch)
        n += len(batch)
    return f"nvjpeg ({torch.cuda.get_device_name()}, batches of 16)", n / (time.perf_counter() - start), size // n


if __name__ == "__main__":
    main()
