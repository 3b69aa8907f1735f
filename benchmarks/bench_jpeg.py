"""JPEG encoding of raw 1280x720 frames: what a recorder of GigE cameras (Mono8/Bayer pixels) pays,
and what the recorder makes of it.

    .venv/bin/python benchmarks/bench_jpeg.py [--frames N] [--quality Q] [--seconds S]

Frames: 1280x720 scenes like the cube's (multi-scale colour texture, black-and-white squares as
tags, sensor noise sigma 2), made here so that the script needs no data files.
Each is also mosaicked to a BayerBG8 frame, what a colour GigE camera hands out.

Encoders, each on one thread (frames per second per core, from the thread's CPU time, so that a
load elsewhere on a shared machine does not lower it):
  opencv      cv2.imencode (libjpeg-turbo in OpenCV's wheels), BGR 4:2:0
  pillow      PIL.Image.save(format="JPEG") (libjpeg-turbo in Pillow's wheels), RGB 4:2:0
  simplejpeg  simplejpeg.encode_jpeg (libjpeg-turbo), BGR 4:2:0, where installed
  turbojpeg   PyTurboJPEG's TurboJPEG.encode (the system's libturbojpeg), BGR 4:2:0, where installed
  bayer+cv2   demosaic (cv2.cvtColor BayerBG2BGR) then cv2.imencode: the whole cost per raw frame
  nvjpeg      torchvision.io.encode_jpeg on CUDA tensors, frames in batches (only with a CUDA GPU and
              torchvision; the upload of the frames is timed with it)
The 53-camera cube at 120 FPS makes 6360 frames/s: the table gives the cores (or GPUs) that takes.

Then the recorder itself (rig.record.Recorder) on raw BayerBG8 frames: 2 fake cameras per core
that hand out frames on a fast virtual clock, so that each reader waits for the writers and the
take goes as fast as the recorder encodes and stores (every frame demosaicked, encoded with the
rig's storage settings, muxed, its frames.csv row written). Beside it the same demosaic + encode
alone, on one thread and on one thread per core. The ratio: the recorder's frames/s per core
over the encoder's alone (goal >= 80 %), and the cores 53 x 120 FPS need; per core is frames per
CPU second, and frames/s on all cores show how far the encoding spreads.
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import os
import shutil
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from rig.cameras import CameraInfo, Frame, TakeCameras
from rig.clock import VirtualClock
from rig.layouts import make_rig
from rig.record import Recorder

CUBE_FPS = 53 * 120
GOAL = 0.80          # the recorder's frames/s per core over the encoder's alone (issue 23)


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
    """(frames per CPU second of this thread, mean bytes per frame) of encode over frames, repeated
    for `seconds`."""
    encode(frames[0])   # warm-up
    n, size, start, cpu = 0, 0, time.perf_counter(), time.thread_time()
    while time.perf_counter() - start < seconds:
        for f in frames:
            size += encode(f)
            n += 1
    return n / (time.thread_time() - cpu), size // n


class RawCamera:
    """A GigE camera's raw frames on a fast virtual clock: read() hands out the next frame at once."""

    def __init__(self, cam_id: str, raws: list[bytes], clock: VirtualClock, t0: int, fps: float) -> None:
        self.id, self.raws, self.clock, self.t0, self.period, self.k = cam_id, raws, clock, t0, 1e9 / fps, 0

    def open(self) -> None: ...

    def configure(self) -> None: ...

    def start(self) -> None: ...

    def stop(self) -> None: ...

    def close(self) -> None: ...

    def trigger(self) -> None: ...

    def info(self) -> CameraInfo:
        return CameraInfo(self.id, "bench", "raw fake", self.id, 1280, 720, 1e9 / self.period, "BayerBG8")

    def read(self, timeout_s: float = 1.0) -> Frame:
        t = self.t0 + int(self.k * self.period)
        self.clock.advance_to(t)
        self.k += 1
        return Frame(self.raws[self.k % len(self.raws)], self.k - 1, t, t, 1280, 720, "bayer_bg8")


class RawTake(NamedTuple):
    frames: int          # stored, every one of them
    wall: float          # seconds
    cpu: float           # CPU seconds of this process
    writers: int         # the recorder's writer threads (one per camera)
    params: list[int]    # cv2.imencode parameters of the rig's storage settings


def record_raw(raws: list[bytes], cameras: int, seconds: float, folder: Path) -> RawTake:
    """One take of `cameras` raw cameras at 120 FPS lasting `seconds` on the virtual clock."""
    rig = make_rig("cube53", cameras=cameras, resolution=(1280, 720), fps=120.0, backend="aravis", seed=0)
    rig = dataclasses.replace(rig, cameras=tuple(dataclasses.replace(c, pixel_format="BayerBG8") for c in rig.cameras))
    clock = VirtualClock(time_scale=0)
    t0 = clock.now_ns() + 1_000_000
    cams = {c.id: RawCamera(c.id, raws, clock, t0, c.fps) for c in rig.cameras}
    recorder = Recorder(rig, folder / "take", "calibration", seconds, TakeCameras(cams, t0_ns=t0), clock)
    cpu, start = os.times(), time.perf_counter()
    result = recorder.run()
    wall, end = time.perf_counter() - start, os.times()
    shutil.rmtree(folder / "take")
    if result.status != "complete" or any(c.seq_gaps or c.overflows for c in result.cameras):
        raise RuntimeError(f"the raw take did not store every frame: {result.reason or result.cameras}")
    writers = sum(s.writer.ident is not None for s in recorder.streams)   # one per camera
    return RawTake(result.frames, wall, end.user - cpu.user + end.system - cpu.system, writers,
                   rig.storage.jpeg_params())


def raw_through_recorder(frames: list[np.ndarray], seconds: float) -> None:
    """The recorder on raw frames against demosaic + encode alone, per core."""
    cores = os.cpu_count() or 1
    mosaics = [bayer(f) for f in frames]
    raws = [m.tobytes() for m in mosaics]
    folder = Path(tempfile.mkdtemp(prefix="bench-jpeg-"))
    try:
        take = record_raw(raws, 2 * cores, seconds, folder)
    finally:
        shutil.rmtree(folder, ignore_errors=True)

    def encode(raw: np.ndarray) -> int:
        return len(cv2.imencode(".jpg", cv2.cvtColor(raw, cv2.COLOR_BayerBG2BGR), take.params)[1])

    one, _ = rate(encode, mosaics)
    # one encoder per core, on the threads cv2 releases the GIL for: what the cores do at best
    batch = mosaics * max(1, 4 * cores // len(mosaics))
    with ThreadPoolExecutor(cores) as pool:
        list(pool.map(encode, batch))
        n, start = 0, time.perf_counter()
        while time.perf_counter() - start < 2.0:
            n += len(list(pool.map(encode, batch)))
        alone = n / (time.perf_counter() - start)
    rec = take.frames / take.wall
    per_core = take.frames / take.cpu
    ratio = per_core / one
    quality = take.params[1]
    chroma = "4:4:4" if take.params[3] == cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444 else "4:2:0"
    print(f"\nraw BayerBG8 1280x720 through the recorder (demosaic + JPEG q{quality} {chroma}, the rig's storage "
          f"settings; {2 * cores} cameras, {take.writers} writer threads on {cores} cores); per core = frames per "
          f"CPU second, which a load elsewhere on the machine does not change:")
    print(f"  encoder alone, one thread:  {one:6.0f} frames/s per core")
    print(f"  encoder alone, {cores} threads:  {alone:6.0f} frames/s ({alone / one:.1f}x one thread)")
    print(f"  recorder:                   {rec:6.0f} frames/s ({rec / one:.1f}x one encoder thread; "
          f"{take.cpu / take.wall:.2f} cores busy), {per_core:.0f} frames/s per core ({take.frames} frames in "
          f"{take.wall:.1f} s)")
    verdict = "met" if ratio >= GOAL else "NOT met"
    print(f"  recorder / encoder alone, per core: {ratio:.0%} (goal >= {GOAL:.0%}: {verdict})")
    print(f"  53 cameras x 120 FPS raw ({CUBE_FPS} frames/s) need {CUBE_FPS / per_core:.0f} cores through the recorder "
          f"({CUBE_FPS / one:.0f} for the encoder alone)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--quality", type=int, default=90)
    parser.add_argument("--seconds", type=float, default=2.5, help="length of the recorder's raw take (virtual time)")
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

    rows = [("opencv", *rate(opencv, frames)), ("pillow", *rate(pillow, frames))]
    missing = []
    for name, make in (("simplejpeg", _simplejpeg), ("turbojpeg", _turbojpeg)):
        encode = make(q)
        if isinstance(encode, str):
            missing.append(f"{name}: {encode}")
        else:
            rows.append((name, *rate(encode, frames)))
    encoders = list(rows)
    rows.append(("bayer+cv2", *rate(bayer_opencv, raws)))
    gpu = _nvjpeg(frames, q)
    print(f"1280x720 frames, quality {q}, 4:2:0; one thread per CPU encoder\n")
    print("| encoder | frames/s per core | KB/frame | cores for 53 x 120 FPS |")
    print("|---|---|---|---|")
    for name, fps, size in rows:
        print(f"| {name} | {fps:.0f} | {size / 1e3:.0f} | {CUBE_FPS / fps:.1f} |")
    if isinstance(gpu, str):
        print(f"\nnvjpeg: {gpu}")
    else:
        name, fps, size = gpu
        print(f"| {name} | {fps:.0f} | {size / 1e3:.0f} | {CUBE_FPS / fps:.2f} GPUs |")
    for line in missing:
        print(line)
    best = max(encoders, key=lambda r: r[1])
    opencv_fps = rows[0][1]
    print(f"\nfastest CPU encoder: {best[0]}; " + ", ".join(f"{name} / opencv {fps / opencv_fps:.2f}"
                                                         for name, fps, _ in encoders[1:])
          + f"; demosaic + encode / encode {rows[-1][1] / opencv_fps:.2f}")
    raw_through_recorder(frames, args.seconds)


def _simplejpeg(quality: int):
    """simplejpeg's encoder as frame -> bytes, or why it was not measured."""
    try:
        import simplejpeg
    except ImportError:
        return "not measured (simplejpeg is not installed)"
    return lambda f: len(simplejpeg.encode_jpeg(f, quality, "BGR", "420"))


def _turbojpeg(quality: int):
    """PyTurboJPEG's encoder as frame -> bytes, or why it was not measured."""
    try:
        from turbojpeg import TJPF_BGR, TJSAMP_420, TurboJPEG
    except ImportError:
        return "not measured (PyTurboJPEG is not installed)"
    try:
        tj = TurboJPEG()   # loads the system's libturbojpeg
    except (OSError, RuntimeError) as exc:
        return f"not measured ({exc})"
    return lambda f: len(tj.encode(f, quality=quality, pixel_format=TJPF_BGR, jpeg_subsample=TJSAMP_420))


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
