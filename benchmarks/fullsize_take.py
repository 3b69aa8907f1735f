"""A full-size take without rendering every frame: the benchmark fixture of issue 23.

    .venv/bin/python benchmarks/fullsize_take.py OUT [--seconds 10] [--cameras 53]
                                                     [--resolution 1280x720] [--fps 120] [--distinct 4]
                                                     [--pace 3]

The simulated cube records the first `--distinct` frames per camera of a grasp take that lasts
`--pace` seconds (JPEG with sensor noise, each camera on its own clock) through the real recorder,
so that from frame to frame the hand moves as it does at the camera's rate in a grasp of that
length: a take of 4 frames would put the whole grasp in them, the hand jumping 30-60 pixels
between frames, which no 120 FPS video shows and which made detect's tracker lose the hand in
every few frames. Each camera's take is then made `--seconds` long in the same format: its JPEG
packets played forward and back (a video whose consecutive frames are consecutive moments, as a
tracker sees one), muxed again by the recorder's own MkvWriter (Cues and all), its frames.csv rows
continued at its own measured frame period (a hardware-triggered take's: the rig's) with its own
device-to-host latency, and take.json's counts, duration and times updated. The simulator's truth
does not hold for the repeated frames, so ground_truth.h5 is left out: this take is for measuring
speed and memory (53 cameras x 1280x720 x 120 FPS x 10 s = 63,600 frames, about 19 GB), not
accuracy.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from manus_core.fileio import write_atomic  # noqa: E402
from manus_core.frames_csv import HEADER, format_row  # noqa: E402
from manus_core.rig_config import RigConfig  # noqa: E402
from manus_core.take import Take  # noqa: E402
from rig.layouts import make_rig  # noqa: E402
from rig.mkv import MkvWriter  # noqa: E402
from rig.record import StopFlag, record_take  # noqa: E402


def back_and_forth(n: int, m: int) -> np.ndarray:
    """n indices into m items, forward and back: 0 1 .. m-1 m-2 .. 1 0 1 .."""
    if m == 1:
        return np.zeros(n, np.int64)
    i = np.arange(n) % (2 * m - 2)
    return np.where(i < m, i, 2 * m - 2 - i)


def record_first_frames(config: RigConfig, session: Path, take: str, kind: str, frames: int, pace_s: float) -> None:
    """Record the first `frames` frames of every camera of a take of `kind` lasting `pace_s`:
    its motion at the pace of that take, without rendering the rest. The take ends as a stopped
    one would; extend() makes it whole."""
    # the count is of all cameras' stored frames together, and the writers of 53 cameras are up to a
    # frame apart when it is reached: one frame a camera more, or one of them has too few for extend()
    stop, want = StopFlag(), (frames + 1) * len(config.cameras)

    def progress(_: str, stored: int, total: int) -> None:
        if stored >= want:
            stop.set(f"the first {frames} frames of each camera")

    record_take(config, session, take, kind, pace_s, stop=stop, progress=progress)


def extend(take_dir: Path, seconds: float, distinct: int | None = None) -> int:
    """Make a recorded take `seconds` long by playing the first `distinct` packets of each camera
    (default: all; the same count in every camera, so that a frame group shows one moment) forward
    and back (0 1 2 3 2 1 0 1 ...: consecutive frames show consecutive moments, as a tracker expects
    of a video); returns its frames."""
    take = Take(take_dir)
    frames = take.frames
    meta = json.loads((take_dir / "take.json").read_text())
    rows, total = [HEADER + "\n"], 0
    end_ns = int(meta.get("t0_ns", meta["start_ns"]) + seconds * 1e9)   # where the take ends
    for entry in meta["cameras"]:
        cam = entry["id"]
        mine = frames["cam"] == cam
        seq, device, host = frames["seq"][mine], frames["t_device_ns"][mine], frames["t_host_ns"][mine]
        # a trigger's period is the rig's; a free-running camera's its own clock's, measured (a few
        # frames' timestamp jitter in the trigger's would drift the cameras apart over the take)
        triggered = meta.get("sync") == "hardware-trigger" or len(device) < 2
        period = 1e9 / meta["fps"] if triggered else float(np.median(np.diff(device)))
        latency = int(np.median(host - device))
        # the recorder keeps reading until a frame arrives at or after the take's end, and keeps it
        n = int(np.ceil((end_ns - device[0] - latency) / period)) + 1
        packets = list(take.packets(cam))[:distinct]
        if distinct and len(packets) < distinct:
            raise SystemExit(f"{take_dir}: camera {cam} recorded {len(packets)} frames, fewer than {distinct}")
        path = take.video_file(cam)
        tmp = path.with_suffix(".extending.mkv")
        writer = MkvWriter(tmp, entry["width"], entry["height"], entry["fps"], name=cam, fsync=False)
        order = back_and_forth(n, len(packets))
        sizes = np.array([len(p) for p in packets])[order]
        for start in range(0, n, 256):   # a batch per system call, as the recorder's writers do
            writer.write([packets[i].tobytes() for i in order[start:start + 256]])
        writer.close()
        tmp.replace(path)
        k = np.arange(n)
        t_device = device[0] + np.rint(k * period).astype(np.int64)
        rows += [format_row(cam, int(seq[0]) + i, int(t_device[i]), int(t_device[i]) + latency,
                            int(sizes[i]), 0) for i in range(n)]
        entry.update(frames=n, bytes=int(sizes.sum()), last_seq=int(seq[0]) + n - 1)
        total += n
    (take_dir / "ground_truth.h5").unlink(missing_ok=True)
    write_atomic(take_dir / "frames.csv", "".join(rows).encode())
    meta.update(frames=total, duration_s=seconds, stop_ns=int(meta["start_ns"] + seconds * 1e9), status="complete",
                reason="")
    write_atomic(take_dir / "take.json", json.dumps(meta, indent=1).encode())
    return total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path, help="session folder to create (the take is OUT/grasp)")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--cameras", type=int, default=53)
    parser.add_argument("--resolution", default="1280x720")
    parser.add_argument("--fps", type=float, default=120.0)
    parser.add_argument("--distinct", type=int, default=4, help="rendered frames per camera")
    parser.add_argument("--pace", type=float, default=3.0,
                        help="length in seconds of the grasp whose first frames are rendered (its pace)")
    args = parser.parse_args()
    size = tuple(int(v) for v in args.resolution.lower().split("x"))
    config = make_rig("cube53", cameras=args.cameras, resolution=size, fps=args.fps, seed=0)
    config = dataclasses.replace(config, sim=dataclasses.replace(config.sim, supersample=1))
    t = time.perf_counter()
    record_first_frames(config, args.out, "grasp", "grasp", args.distinct, args.pace)
    print(f"rendered and recorded {args.distinct} frames a camera in {time.perf_counter() - t:.0f} s")
    t = time.perf_counter()
    frames = extend(args.out / "grasp", args.seconds, args.distinct)
    gb = sum(p.stat().st_size for p in (args.out / "grasp" / "cams").glob("*.mkv")) / 1e9
    print(f"{args.out / 'grasp'}: {len(config.cameras)} cameras x {size[0]}x{size[1]} x {args.fps:g} FPS x "
          f"{args.seconds:g} s = {frames} frames, {gb:.2f} GB, extended in {time.perf_counter() - t:.0f} s")


if __name__ == "__main__":
    main()
