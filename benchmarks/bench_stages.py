"""Every stage that reads a take, on full-size takes of two lengths, against decoding alone.

    .venv/bin/python benchmarks/bench_stages.py [--cameras 4] [--seconds 2 10] [--keep DIR]

A hand take and an empty-cube take of `--cameras` cameras at 1280x720 and 120 FPS are rendered
and recorded (the first 4 frames a camera of a hand routine 10 s long, whose first pose is held:
at 120 FPS consecutive frames differ by the sensor's noise) and made `--seconds` long by
benchmarks/fullsize_take.py's `extend` (the real format: MkvWriter with Cues, frames.csv at each
camera's own clock). On each length, one process per stage, pinned to one CPU core with one
thread for numpy, OpenCV and onnxruntime, runs through the command line as a user would:

    decode (ffmpeg)     ffmpeg -threads 1 -i CAM.mkv -f null -, camera after camera: the floor
    decode (Take)       Take.iter_frames over every camera: the toolkit's reader and its decoder
                        (simplejpeg: libjpeg-turbo)
    sync-report         frame groups and the files' checks (element headers only, nothing decoded)
    detect              palm detector and hand keypoints (ONNX, tracked) on every frame
    detect (int8)       the same with the int8 landmark model (`models quantize`, calibrated on the
                        shortest hand take, in a model cache of the benchmark's own)
    annotate            triangulation, IK and the 1-euro filter from keypoints2d.h5, without the
                        cross-view step (which reads the frames of the views the palm detector
                        missed and runs the landmark model twice on each: docs/annotate.md)
    segment             hand masks of every frame group, every camera, into DATASET.h5
    reconstruct hand    MANUS-Hand trained on crops of 6 poses, 100 steps (counted in steps: its
                        work does not grow with the take)
    contacts            every frame group's hand Gaussians against an object's (a sphere of
                        Gaussians where the hand is: contacts reads no image, and its cost is the
                        same whatever the object), counted in frames as segment is

Before them, segment runs once on the shortest take, timed apart: the first run after an install
compiles the numba loops of segmentation (manus_core/jit.py) and caches them on disk, 6-7 s that
every later run loads in a fraction of a second; counted in the 2 s take's figure, they made it
half as fast as it is.

Printed per stage and length: frames, seconds, frames/s on the one core, its share of decoding's
(ffmpeg's) rate, and peak memory (the process's largest resident set, from wait4); then the
growth from the shortest to the longest take: time (linear: 5x for 2 s -> 10 s, goal <= 5.5x)
and peak memory (constant: goal <= 1.2x). The calibration is the simulator's true cameras and the
bones the subject's: this measures speed and memory, not accuracy (tests and the demo calibrate
from the images and estimate the bones).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE)]

import numpy as np  # noqa: E402
from fullsize_take import extend, record_first_frames  # noqa: E402
from int8_cache import quantized_cache  # noqa: E402

from dataset_tools.hand.bones import BoneLengths, save_subject  # noqa: E402
from manus_core.dataset import read_dataset  # noqa: E402
from manus_core.take import Take  # noqa: E402
from rig.layouts import make_rig  # noqa: E402
from rig.record import record_take  # noqa: E402
from rig.sim.cube import true_cameras  # noqa: E402
from rig.sim.hand import make_hand  # noqa: E402

BIN = Path(sys.executable).parent
# onnxruntime itself reads none of these; the toolkit's sessions take OMP_NUM_THREADS (keypoints/runtime.py).
# Before they did, onnxruntime's threads ran on the other core, and detect's figures were two cores'.
ONE_THREAD = {v: "1" for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS",
                               "OPENCV_FOR_THREADS_NUM")}
FLOOR_SHARE = 0.5      # every stage that reads frames at >= 50 % of decoding's rate (issue 23)
STEPS = 100            # reconstruct hand's training steps
# triggered together, so that a frame group's repeated frames show one moment in every camera (free-running
# cameras pair one camera's first rendered frame with another's third, and triangulation mixes moments)
SYNC = "hardware-trigger"
DISTINCT = 4           # rendered frames a camera
HAND_PACE_S = 10.0     # the hand routine's length (docs/scale.md)
TIME_GROWTH, MEMORY_GROWTH = 5.5 / 5, 1.2
# A small process starts each stage, so that its peak memory (wait4's) is not the benchmark's: a
# forked child's high-water mark starts at its parent's size and survives exec.
LAUNCH = ("import os, sys\nos.sched_setaffinity(0, {int(sys.argv[1])})\npid = os.fork()\nif pid == 0:\n"
          "    os.execvp(sys.argv[3], sys.argv[3:])\n_, status, usage = os.wait4(pid, 0)\n"
          "open(sys.argv[2], 'w').write(str(usage.ru_maxrss))\nsys.exit(os.waitstatus_to_exitcode(status))\n")
DECODE = ("import sys\nfrom manus_core.take import Take\nt = Take(sys.argv[1])\n"
          "for cam in t.cameras:\n    for _ in t.iter_frames(cam):\n        pass\n")


@dataclasses.dataclass
class Run:
    stage: str
    seconds: float
    frames: int        # frames of the take it went through, or training steps (unit)
    wall_s: float
    rss_mb: float
    unit: str = "frames"

    @property
    def fps(self) -> float:
        return self.frames / self.wall_s


def make_takes(root: Path, cameras: int, lengths: list[float]) -> dict[float, Path]:
    """A session per length: hand take, empty cube (the background), the true calibration."""
    config = make_rig("cube53", cameras=cameras, resolution=(1280, 720), fps=120.0, seed=0, sync=SYNC)
    config = dataclasses.replace(config, sim=dataclasses.replace(config.sim, supersample=1))
    base = root / "base"
    t = time.perf_counter()
    # the hand's frames are the first of its routine at a person's pace, each pose held about a second
    record_first_frames(config, base, "hand", "hand", DISTINCT, HAND_PACE_S)
    record_take(config, base, "empty", "calibration", DISTINCT / config.fps)
    true_cameras(config).save(base / "cameras.json")
    # the subject's own bones: a few detected cameras are no basis for estimating them, nor the point
    # here; with another hand's, the fitted hand misses the masks and reconstruct finds no view
    bones = make_hand(config.sim.subject).skeleton.bone_lengths
    save_subject(base / "bones.json", config.sim.subject, BoneLengths(np.asarray(bones), np.full(20, np.nan),
                                                                      np.zeros(20, int)))
    print(f"rendered and recorded 2 x {cameras} x {DISTINCT} frames at 1280x720 in {time.perf_counter() - t:.0f} s",
          flush=True)
    sessions = {}
    for seconds in lengths:
        session = root / f"{seconds:g}s"
        shutil.copytree(base, session)
        t = time.perf_counter()
        frames = extend(session / "hand", seconds, DISTINCT)
        gb = sum(p.stat().st_size for p in (session / "hand" / "cams").glob("*.mkv")) / 1e9
        print(f"{session / 'hand'}: {frames} frames, {gb:.2f} GB, made in {time.perf_counter() - t:.0f} s", flush=True)
        sessions[seconds] = session
    return sessions


def measure(stage: str, argv: list[str], seconds: float, frames: int, cpu: int, log: Path, unit: str = "frames") -> Run:
    """Run one stage's process on core `cpu`; its wall time and peak resident memory."""
    env = {**os.environ, **ONE_THREAD}
    peak = log.with_suffix(".rss")
    with open(log, "ab") as out:
        out.write(f"\n$ {' '.join(argv)}\n".encode())
        out.flush()
        start = time.perf_counter()
        code = subprocess.run([sys.executable, "-c", LAUNCH, str(cpu), str(peak), *argv], stdout=out, stderr=out,
                              env=env).returncode
        wall = time.perf_counter() - start
    if code not in (0, 1):   # sync-report exits 1 on a failing verdict, which still ran
        raise SystemExit(f"{stage} failed (exit {code}); see {log}")
    return Run(stage, seconds, frames, wall, int(peak.read_text()) / 1024, unit)


def stages(session: Path, seconds: float, cpu: int, log: Path) -> list[Run]:
    take, calib = session / "hand", session / "cameras.json"
    opened = Take(take)
    frames = sum(opened.frame_count(c) for c in opened.cameras)
    ffmpeg = " && ".join(f"ffmpeg -v error -threads 1 -i {opened.video_file(c)} -f null -" for c in opened.cameras)
    cli = str(BIN / "manus-capture")
    runs = [measure("decode (ffmpeg)", ["bash", "-c", ffmpeg], seconds, frames, cpu, log),
            measure("decode (Take)", [sys.executable, "-c", DECODE, str(take)], seconds, frames, cpu, log),
            measure("sync-report", [cli, "sync-report", str(take)], seconds, frames, cpu, log),
            measure("detect", [cli, "detect", str(take), "--force"], seconds, frames, cpu, log),
            measure("detect (int8)", [cli, "detect", str(take), "--model", "mediapipe-hand-int8",
                                      "-o", str(session / "keypoints_int8.h5")], seconds, frames, cpu, log),
            measure("annotate", [cli, "annotate", str(take), "--calib", str(calib), "--keypoints", "file",
                                 "--no-cross-view", "--bones", str(session / "bones.json"),
                                 "-o", str(session / "dataset.h5")],
                    seconds, frames, cpu, log)]
    groups = len(np.load(take / "frame_groups.npz")["frame_ns"])
    dataset = session / "dataset.h5"
    views = groups * len(opened.cameras)
    runs.append(measure("segment", segment_argv(session, dataset), seconds, views, cpu, log))
    runs.append(measure("reconstruct hand", [cli, "reconstruct", "hand", "--take", str(take), "--dataset", str(dataset),
                                             "--cameras", str(calib), "--poses", "6", "--iterations", str(STEPS),
                                             "--threads", "1", "-o", str(session / "hand.pt"), "--force"],
                        seconds, STEPS, cpu, log, unit="steps"))
    data = read_dataset(dataset)
    key = data.takes[0]
    sphere_object(session / "object.pt", np.nanmean(data[key].keypoints3d, axis=(0, 1)))
    runs.append(measure("contacts", [cli, "contacts", str(dataset), "--take", key, "--hand", str(session / "hand.pt"),
                                     "--object", str(session / "object.pt"), "--device", "cpu"],
                        seconds, views, cpu, log))
    return runs


def first_segment(session: Path, cpu: int, log: Path) -> float:
    """segment once on `session`, untimed by the table: the first run after an install compiles
    its numba loops (manus_core/jit.py) and caches them on disk, which every later run loads; its
    seconds are printed apart, so that the table measures what a run costs once installed."""
    out = session / "first_segment.h5"
    run = measure("segment (first)", segment_argv(session, out), 0, 0, cpu, log)
    out.unlink()
    return run.wall_s


def segment_argv(session: Path, out: Path) -> list[str]:
    """The segment command on a session's hand take, against its empty cube, into `out`."""
    return [str(BIN / "manus-capture"), "segment", str(session / "hand"), "--calib", str(session / "cameras.json"),
            "--background", str(session / "empty"), "-o", str(out)]


def sphere_object(path: Path, centre: np.ndarray, radius: float = 0.04, count: int = 4000) -> None:
    """An object checkpoint: `count` Gaussians on a sphere around `centre` (where the hand is)."""
    import torch

    from manus_capture.splat.checkpoint import save_checkpoint
    from manus_capture.splat.gaussians import Gaussians

    rng = np.random.default_rng(0)
    directions = rng.standard_normal((count, 3))
    points = centre + radius * directions / np.linalg.norm(directions, axis=1, keepdims=True)
    save_checkpoint(path, Gaussians.from_points(torch.as_tensor(points, dtype=torch.float32), sh_degree=0),
                    kind="object")


def report(runs: list[Run], lengths: list[float]) -> None:
    floor = {r.seconds: r.fps for r in runs if r.stage == "decode (ffmpeg)"}
    print(f"\n{'stage':<16} {'take':>5} {'frames':>7} {'s':>8} {'frames/s/core':>14} {'of decode':>10} {'peak MB':>8}")
    for r in runs:
        share = f"{r.fps / floor[r.seconds]:>9.0%}" if r.unit == "frames" else f"{r.unit + '/s':>9}"
        goal = "" if r.unit != "frames" or r.stage.startswith("decode") else \
            "  ok" if r.fps >= FLOOR_SHARE * floor[r.seconds] else f"  below {FLOOR_SHARE:.0%}"
        print(f"{r.stage:<16} {r.seconds:>4g}s {r.frames:>7} {r.wall_s:>8.1f} {r.fps:>14.1f} "
              f"{share} {r.rss_mb:>8.0f}{goal}")
    short, long = min(lengths), max(lengths)
    if short == long:
        return
    print(f"\ngrowth {short:g} s -> {long:g} s (linear time: {long / short:g}x, "
          f"goal <= {TIME_GROWTH * long / short:g}x; constant memory: goal <= {MEMORY_GROWTH:g}x)")
    by = {(r.stage, r.seconds): r for r in runs}
    for stage in dict.fromkeys(r.stage for r in runs):
        a, b = by[stage, short], by[stage, long]
        time_ratio, rss_ratio = b.wall_s / a.wall_s, b.rss_mb / a.rss_mb
        ok = time_ratio <= TIME_GROWTH * long / short and rss_ratio <= MEMORY_GROWTH
        print(f"{stage:<16} time {time_ratio:5.2f}x  peak memory {rss_ratio:5.2f}x  {'ok' if ok else 'MISSED'}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cameras", type=int, default=4)
    parser.add_argument("--seconds", type=float, nargs="+", default=[2.0, 10.0])
    parser.add_argument("--keep", type=Path, default=None, help="make the takes here and keep them")
    args = parser.parse_args()
    root = args.keep or Path(tempfile.mkdtemp(prefix="bench_stages_"))
    cpu = min(os.sched_getaffinity(0))
    try:
        sessions = make_takes(root, args.cameras, args.seconds)
        quantized_cache(root, [sessions[min(sessions)] / "hand"], root / "stages.log")
        first = first_segment(sessions[min(sessions)], cpu, root / "stages.log")
        print(f"segment's first run on this install (compiling its loops): {first:.1f} s", flush=True)
        runs = []
        for seconds, session in sessions.items():
            runs += stages(session, seconds, cpu, root / "stages.log")
            print(f"{seconds:g} s take: done", flush=True)
        report(runs, args.seconds)
    finally:
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
