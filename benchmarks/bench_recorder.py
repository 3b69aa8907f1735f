"""Recorder throughput: the largest aggregate frame rate recorded with zero drops, next to a plain
file append of the same JPEG bytes (what any recorder sits on), measured in the same run.

Cameras are fakes that hand out pre-encoded 1280x720 JPEG frames (rendered by the simulated cube)
on their own schedule, as a UVC camera does: a frame is ready every 1/fps s and the camera keeps
the last BUFFERS frames; a reader that falls further behind loses frames (seq gaps). Every camera
runs at 120 FPS (the MANUS cube's rate, so each keeps its real latency budget of BUFFERS frame
periods); the number of cameras is searched, from the cube's 53, for the most that record
without a single lost frame. Both sides write into the page cache (the files are fsynced after the
timed part); a take longer than the machine's dirty-page budget runs at the disk's sustained
speed instead, which the "append + fsync" line shows.

A second search, take by take in turn with the first, records with the live monitor (`record
--monitor`) serving the take to a page that polls it: /api/status and every camera's thumbnail
each POLL_S, as the page refreshes. The page is another process (a browser is never in the recorder's process, and a poller thread
there would add GIL contention the recorder never sees); the server, its sampling of the
recorder and its thumbnail decodes are in the recorder's process, as with `record --monitor`.
The zero-drop camera count with the monitor should be >= 95 % of the count without.

    .venv/bin/python benchmarks/bench_recorder.py [--fps 120] [--seconds 2] [--out DIR] [--no-monitor]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import multiprocessing
import os
import shutil
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from multiprocessing.sharedctypes import Synchronized
from pathlib import Path

from manus_capture.monitor import start_monitor
from rig.cameras import CameraInfo, Frame, TakeCameras
from rig.clock import MonotonicClock
from rig.layouts import make_rig
from rig.record import Recorder
from rig.sim.cube import SimulatedCube

BUFFERS = 4          # frames a UVC camera keeps for the host (the driver's default queue)
TARGET_FPS = 120.0
TARGET_CAMERAS = 53
POLL_S = 0.25        # the page's refresh: its status and every thumbnail this often
MONITOR_GOAL = 0.95  # zero-drop cameras with the monitor / without (issue 24)


def sample_frames(n: int = 4) -> list[bytes]:
    """n 1280x720 JPEGs of the simulated cube (q90, sensor noise): ~165 KB each."""
    rig = make_rig("cube53", cameras=1, resolution=(1280, 720), seed=0)
    cam = SimulatedCube(rig, "calibration", 1.0).camera(rig.cameras[0].id)
    cam.open()
    cam.start()
    return [cam.read().data for _ in range(n)]


class PacedCamera:
    """Hands out pre-encoded frames at `fps` on CLOCK_MONOTONIC, keeping the last BUFFERS."""

    def __init__(self, cam_id: str, frames: list[bytes], fps: float) -> None:
        self.id, self.frames, self.period = cam_id, frames, 1e9 / fps
        self.k = 0
        self.t0 = 0

    def open(self) -> None: ...

    def configure(self) -> None: ...

    def start(self) -> None:
        self.t0 = time.monotonic_ns() + 5_000_000

    def stop(self) -> None: ...

    def close(self) -> None: ...

    def trigger(self) -> None: ...

    def info(self) -> CameraInfo:
        return CameraInfo(self.id, "bench", "paced fake", self.id, 1280, 720, 1e9 / self.period, "MJPG")

    def read(self, timeout_s: float = 1.0) -> Frame | None:
        ready = self.t0 + self.k * self.period
        wait = (ready - time.monotonic_ns()) / 1e9
        if wait > timeout_s:
            time.sleep(timeout_s)
            return None
        if wait > 0:
            time.sleep(wait)
        now = time.monotonic_ns()
        newest = int((now - self.t0) // self.period)
        self.k = max(self.k, newest - BUFFERS + 1)   # older frames were overwritten in the camera
        k, self.k = self.k, self.k + 1
        t = int(self.t0 + k * self.period)
        return Frame(self.frames[k % len(self.frames)], k, t, now, 1280, 720, "jpeg")


def plain_append(frames: list[bytes], folder: Path, seconds: float) -> tuple[float, float]:
    """Frames per second of one thread appending the frames to one file: (page cache, + fsync)."""
    path = folder / "append.bin"
    n = 0
    with open(path, "wb") as f:
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            for data in frames:
                f.write(data)
            n += len(frames)
        f.flush()
        written = time.perf_counter() - t0
        os.fsync(f.fileno())
        synced = time.perf_counter() - t0
    path.unlink()
    return n / written, n / synced


def poll_page(url: str, cams: list[str], ready, done, served) -> None:
    """A page open on the monitor at `url`: /api/status, then every camera's thumbnail, each POLL_S,
    one request after the other on one connection at a time (as a browser's few connections do);
    `served` counts the thumbnails that came back."""
    while not done.is_set():
        t = time.monotonic()
        with urllib.request.urlopen(url + "api/status", timeout=5) as r:
            r.read()
        for cam in cams:
            with urllib.request.urlopen(f"{url}api/cameras/{cam}/latest.jpg", timeout=5) as r:
                if r.status == 200 and r.read():
                    served.value += 1
        ready.set()
        done.wait(max(0.0, POLL_S - (time.monotonic() - t)))


@contextlib.contextmanager
def page_open(recorder: Recorder) -> Iterator[Synchronized]:
    """The monitor serving `recorder.live` on a free loopback port, and a page polling it until the
    block ends; yields the count of thumbnails the page received."""
    server = start_monitor(recorder.live, "127.0.0.1", 0)
    ctx = multiprocessing.get_context("spawn")
    ready, done, served = ctx.Event(), ctx.Event(), ctx.Value("l", 0)
    page = ctx.Process(target=poll_page, args=(server.url, recorder.live.camera_ids(), ready, done, served))
    page.start()
    try:
        if not ready.wait(30):
            raise RuntimeError(f"the page did not get the monitor's status from {server.url}")
        yield served
    finally:
        done.set()
        page.join(10)
        server.stop()


def record(frames: list[bytes], folder: Path, cameras: int, fps: float, seconds: float,
           monitor: bool = False) -> tuple[int, int, float, int]:
    """(frames stored, frames lost, wall seconds, thumbnails served) of one take of `cameras` paced
    cameras; `monitor`: with the monitor serving the take to a page polling it."""
    rig = make_rig("cube53", resolution=(1280, 720), fps=fps, backend="v4l2", seed=0)
    # beyond the 53 cameras of the layout, more of the same with their own ids
    configs = tuple(dataclasses.replace(rig.cameras[i % len(rig.cameras)], id=f"cam{i:03d}") for i in range(cameras))
    rig = dataclasses.replace(rig, cameras=configs)
    cams = {c.id: PacedCamera(c.id, frames, fps) for c in configs}
    take = folder / f"take-{cameras}"
    recorder = Recorder(rig, take, "calibration", seconds, TakeCameras(cams), MonotonicClock())
    with page_open(recorder) if monitor else contextlib.nullcontext() as served:
        t = time.perf_counter()
        result = recorder.run()
        wall = time.perf_counter() - t
    shutil.rmtree(take)
    lost = sum(c.seq_gaps + c.unwritten for c in result.cameras)
    return result.frames, lost, wall, served.value if monitor else 0


class Search:
    """The most cameras at `fps` that record without a lost frame: from `start` up by half while
    lossless (until `ceiling` frames/s) or down by half, then bisect to 5 %. `n` is the count to
    try next; add() takes its outcome."""

    def __init__(self, start: int, fps: float, ceiling: float) -> None:
        self.n, self.fps, self.ceiling = start, fps, ceiling
        self.good, self.bad = 0, None
        self.done = False

    def add(self, lost: int) -> None:
        n = self.n
        if lost == 0:
            self.good = n
        else:
            self.bad = n
        if self.bad is None:
            self.done = n * self.fps > self.ceiling
            self.n = n * 3 // 2
        elif self.bad - self.good <= max(1, self.good // 20):
            self.done = True
        else:
            self.n = (self.good + self.bad) // 2 if self.good else self.bad // 2


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fps", type=float, default=TARGET_FPS, help="frame rate of every camera")
    ap.add_argument("--seconds", type=float, default=2.0, help="length of each recorded take")
    ap.add_argument("--out", type=Path, default=None, help="folder on the disk to test (default: a temp dir)")
    ap.add_argument("--no-monitor", action="store_true", help="skip the search with the live monitor")
    args = ap.parse_args()
    frames = sample_frames()
    size = sum(map(len, frames)) / len(frames)
    folder = Path(tempfile.mkdtemp(prefix="bench-recorder-", dir=args.out))
    try:
        print(f"frames: 1280x720 JPEG, {size / 1e3:.0f} KB mean; cameras keep {BUFFERS} frames; "
              f"{os.cpu_count()} CPUs; disk {folder}")
        # the baseline is taken before, during and after the search, and the best of the three is
        # the reference: on a shared machine this errs against the recorder
        baselines = [plain_append(frames, folder, args.seconds)]
        ceiling = 2.5 * baselines[0][0]
        # cameras at args.fps, from 53; without and with the monitor in turn, so that a load from
        # elsewhere on a shared machine falls on both searches alike
        searches = {monitor: Search(TARGET_CAMERAS, args.fps, ceiling) for monitor in (False, True)
                    if not (monitor and args.no_monitor)}
        while not all(s.done for s in searches.values()):
            for monitor, search in searches.items():
                if search.done:
                    continue
                n = search.n
                stored, lost, wall, served = record(frames, folder, n, args.fps, args.seconds, monitor)
                verdict = "no drops" if lost == 0 else f"{lost} lost"
                page = f", page got {served} thumbnails" if monitor else ""
                print(f"  recorder{' + monitor' if monitor else ''}, {n:3d} cameras x {args.fps:g} FPS = "
                      f"{n * args.fps:6.0f} frames/s: {stored} frames stored, {verdict} ({wall:.1f} s{page})")
                search.add(lost)
                if lost and len(baselines) == 1:
                    baselines.append(plain_append(frames, folder, args.seconds))
        baselines.append(plain_append(frames, folder, args.seconds))
        good = searches[False].good
        cached, synced = max(b[0] for b in baselines), max(b[1] for b in baselines)
        print(f"plain file append (one thread, one file; best of {len(baselines)}): {cached:.0f} frames/s "
              f"({cached * size / 1e9:.2f} GB/s); with fsync {synced:.0f} frames/s ({synced * size / 1e9:.2f} GB/s)")
        best = good * args.fps
        print(f"recorder, zero drops: {best:.0f} frames/s = {good} cameras x {args.fps:g} FPS "
              f"({best * size / 1e9:.2f} GB/s); {best / cached:.0%} of the plain append (goal >= 80%)")
        need = TARGET_CAMERAS * TARGET_FPS
        if best >= need:
            print(f"{TARGET_CAMERAS} cameras x {TARGET_FPS:g} FPS ({need:.0f} frames/s) fit on this machine")
        else:
            print(f"{TARGET_CAMERAS} cameras x {TARGET_FPS:g} FPS ({need:.0f} frames/s) do NOT fit on this machine; "
                  f"it records {int(best // TARGET_FPS)} cameras at {TARGET_FPS:g} FPS, or {TARGET_CAMERAS} cameras "
                  f"at {best / TARGET_CAMERAS:.0f} FPS")
        if True in searches:
            watched = searches[True].good
            ratio = watched / good if good else float(watched == 0)
            print(f"with the monitor and a page polling every {POLL_S:g} s: {watched} cameras x {args.fps:g} FPS "
                  f"with zero drops, without: {good}; {ratio:.0%} (goal >= {MONITOR_GOAL:.0%})")
    finally:
        shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    main()
