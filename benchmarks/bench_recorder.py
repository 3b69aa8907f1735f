"""Recorder throughput: the largest aggregate frame rate recorded with zero drops, next to a plain
file append of the same JPEG bytes (what any recorder sits on), measured in the same run.

Cameras are fakes that hand out pre-encoded 1280x720 JPEG frames (rendered by the simulated cube)
on their own schedule, as a UVC camera does: a frame is ready every 1/fps s and the camera keeps
the last BUFFERS frames; a reader that falls further behind loses frames (seq gaps). Every camera
runs at 120 FPS (the MANUS cube's rate, so each keeps its real latency budget of BUFFERS frame
periods); the number of cameras is searched, from the cube's 53, for the most that record
without a single lost frame.

Where: by default the disk's temporary folder, as a take is recorded; --ram records into a RAM
file system (/dev/shm) where it has room, so that both sides measure what the path costs in CPU,
which is what the recorder decides. A disk's page cache takes only so
many dirty bytes (vm.dirty_background_ratio of the memory, about 2 GB on a 24 GB machine) before
the kernel writes back, and past about 1.5 times that it holds every writer until the disk
catches up: 2 s at the rates searched here are 3 to 5 GB, so on a disk that is slower than the
rate the search finds the disk's writeback, not the recorder (docs/recording.md, "Speed").
--out DIR measures another disk. On a disk the "with fsync" figure is its sustained speed. Every
take and every baseline starts with the page cache written back (os.sync(), not timed), as a take
does that follows the last by the seconds an operator needs between grasps: back to back, a take
started while the kernel was still writing the last one's gigabytes lost frames with as few as 16
cameras.

A second search (in the first run), take by take in turn with the first, records with the live monitor (`record
--monitor`) serving the take to a page that polls it: /api/status and every camera's thumbnail
each POLL_S, as the page refreshes. The page is another process (a browser is never in the
recorder's process, and a poller thread there would add GIL contention the recorder never sees);
the server, its sampling of the recorder and its thumbnail decodes are in the recorder's process,
as with `record --monitor`.
The zero-drop camera count with the monitor should be >= 95 % of the count without.

The whole measurement (baseline and search) runs --runs times in a row, each search starting
from the count the run before found, and the min, median and max over the runs are printed: a
recorder that keeps up only now and then shows in the min. The goal, >= 80 % of the plain
append, holds for every run or it is missed. A lost frame is counted where it was lost: by the
camera (its reader came back too late: the camera's BUFFERS frames were overwritten) or by the
host's ring (the writers fell half a second behind).

    .venv/bin/python benchmarks/bench_recorder.py [--fps 120] [--seconds 2] [--runs 5] [--out DIR | --ram]
        [--no-monitor]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import multiprocessing
import os
import shutil
import statistics
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from multiprocessing.sharedctypes import Synchronized
from pathlib import Path
from typing import Self

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
RAM_DIR = Path("/dev/shm")
RAM_SHARE = 0.4      # the largest take may fill this share of the RAM file system's free space
GOAL = 0.80          # zero-drop frame rate / plain append, in every run (issue 23)


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


class Load:
    """CPUs the rest of the machine kept busy while a block ran: other processes, and the kernel's
    writeback of what this one wrote (from /proc/stat, less this process's own CPU time). On a
    shared machine it tells a take that lost frames to a neighbour's load from one that did not."""

    def __init__(self) -> None:
        self.others: float | None = None

    @staticmethod
    def _busy() -> float | None:
        try:
            with open("/proc/stat") as f:
                ticks = [int(x) for x in f.readline().split()[1:9]]
        except OSError:
            return None
        # user nice system idle iowait irq softirq steal: all but idle and iowait
        return (sum(ticks) - ticks[3] - ticks[4]) / os.sysconf("SC_CLK_TCK")

    def __enter__(self) -> Self:
        self._t, self._busy0, self._own = time.perf_counter(), self._busy(), os.times()
        return self

    def __exit__(self, *exc: object) -> None:
        busy, own = self._busy(), os.times()
        if busy is not None and self._busy0 is not None:
            mine = own.user - self._own.user + own.system - self._own.system
            self.others = max(0.0, busy - self._busy0 - mine) / (time.perf_counter() - self._t)

    def __str__(self) -> str:
        return "" if self.others is None else f"; rest of the machine {self.others:.1f} CPUs"


def file_system(folder: Path) -> str:
    """The type of the file system that holds `folder` (tmpfs, ext4, ...), from /proc/mounts."""
    best, kind = "", "unknown"
    with contextlib.suppress(OSError), open("/proc/mounts") as f:
        for line in f:
            _, mount, fstype = line.split()[:3]
            if str(folder).startswith(mount.rstrip("/") + "/") and len(mount) > len(best):
                best, kind = mount, fstype
    return kind


def take_folder(out: Path | None, ram: bool, bytes_per_s: float, seconds: float) -> tuple[Path, float]:
    """(where the takes go, the most frames/s x bytes a take there may write per second): `out`,
    with `ram` the RAM file system where it holds the largest take the search may try, else the
    disk's temporary folder."""
    if out is not None:
        return out, float("inf")
    if ram and RAM_DIR.is_dir() and os.access(RAM_DIR, os.W_OK):
        # its pages are memory: the smaller of its own free space and the machine's free memory
        free = min(shutil.disk_usage(RAM_DIR).free, os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
        room = free * RAM_SHARE / seconds
        if room >= 1.5 * TARGET_CAMERAS * TARGET_FPS * bytes_per_s:
            return RAM_DIR, room
    return Path(tempfile.gettempdir()), float("inf")


def plain_append(frames: list[bytes], folder: Path, seconds: float) -> tuple[float, float]:
    """Frames per second of one thread appending the frames to one file: (page cache, + fsync)."""
    path = folder / "append.bin"
    n = 0
    os.sync()
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


@dataclasses.dataclass(frozen=True)
class Outcome:
    """One take: frames stored, lost (by the camera or the host), of those lost to a full ring,
    wall seconds, thumbnails a monitoring page received, the rest of the machine's load."""

    stored: int
    lost: int
    overflows: int
    wall: float
    served: int
    load: Load


def record(frames: list[bytes], folder: Path, cameras: int, fps: float, seconds: float,
           monitor: bool = False) -> Outcome:
    """One take of `cameras` paced cameras; `monitor`: with the monitor serving the take to a page
    polling it."""
    rig = make_rig("cube53", resolution=(1280, 720), fps=fps, backend="v4l2", seed=0)
    # beyond the 53 cameras of the layout, more of the same with their own ids
    configs = tuple(dataclasses.replace(rig.cameras[i % len(rig.cameras)], id=f"cam{i:03d}") for i in range(cameras))
    rig = dataclasses.replace(rig, cameras=configs)
    cams = {c.id: PacedCamera(c.id, frames, fps) for c in configs}
    take = folder / f"take-{cameras}"
    os.sync()
    recorder = Recorder(rig, take, "calibration", seconds, TakeCameras(cams), MonotonicClock())
    with page_open(recorder) if monitor else contextlib.nullcontext() as served, Load() as load:
        t = time.perf_counter()
        result = recorder.run()
        wall = time.perf_counter() - t
    shutil.rmtree(take)
    # a full ring at the very end of a take leaves no gap after it: the larger of the two counts
    lost = sum(max(c.seq_gaps, c.overflows) + c.unwritten for c in result.cameras)
    return Outcome(result.frames, lost, sum(c.overflows for c in result.cameras), wall,
                   served.value if monitor else 0, load)


class Search:
    """The most cameras at `fps` that record without a lost frame: from `start` up by `step` while
    lossless (until `ceiling` frames/s) or down by half, then bisect to the camera (to 5 %, a camera
    or two of 50, a run's figure was a lower bound by up to 4 %). `n` is the count to try next;
    add() takes its outcome."""

    def __init__(self, start: int, fps: float, ceiling: float, step: float = 1.5) -> None:
        self.n, self.fps, self.ceiling, self.step = start, fps, ceiling, step
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
            self.n = max(n + 1, int(n * self.step))
        elif self.bad - self.good <= 1:
            self.done = True
        else:
            self.n = (self.good + self.bad) // 2 if self.good else self.bad // 2


@dataclasses.dataclass(frozen=True)
class Run:
    """One run: zero-drop cameras without and with the monitor (None: not searched), and the
    plain append in frames/s (page cache, with fsync), best of the run's baselines."""

    good: int
    watched: int | None
    cached: float
    synced: float


def one_run(frames: list[bytes], folder: Path, args: argparse.Namespace, start: int, step: float, monitor: bool,
            room: float) -> Run:
    """Search from `start` cameras up by `step`; `room`: bytes per second a take may write (a RAM
    file system holds only so much)."""
    # the baseline is taken before, during and after the search, and the best of the three is
    # the reference: on a shared machine this errs against the recorder
    baselines = [plain_append(frames, folder, args.seconds)]
    size = sum(map(len, frames)) / len(frames)
    ceiling = min(2.5 * baselines[0][0], room / size)
    # without and with the monitor in turn, so that a load from elsewhere on a shared machine
    # falls on both searches alike
    searches = {watch: Search(start, args.fps, ceiling, step) for watch in (False, True) if monitor or not watch}
    while not all(s.done for s in searches.values()):
        for watch, search in searches.items():
            if search.done:
                continue
            n = search.n
            take = record(frames, folder, n, args.fps, args.seconds, watch)
            verdict = "no drops" if take.lost == 0 else f"{take.lost} lost"
            if take.overflows:
                verdict += f" ({take.overflows} by a full ring)"
            page = f", page got {take.served} thumbnails" if watch else ""
            print(f"  recorder{' + monitor' if watch else ''}, {n:3d} cameras x {args.fps:g} FPS = "
                  f"{n * args.fps:6.0f} frames/s: {take.stored} frames stored, {verdict} "
                  f"({take.wall:.1f} s{page}{take.load})")
            search.add(take.lost)
            if take.lost and len(baselines) == 1:
                baselines.append(plain_append(frames, folder, args.seconds))
    baselines.append(plain_append(frames, folder, args.seconds))
    return Run(searches[False].good, searches[True].good if True in searches else None,
               max(b[0] for b in baselines), max(b[1] for b in baselines))


def spread(values: list[float], fmt: str) -> str:
    return " / ".join(format(v, fmt) for v in (min(values), statistics.median(values), max(values)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fps", type=float, default=TARGET_FPS, help="frame rate of every camera")
    ap.add_argument("--seconds", type=float, default=2.0, help="length of each recorded take")
    ap.add_argument("--runs", type=int, default=5, help="measurements in a row (min, median and max are shown)")
    ap.add_argument("--out", type=Path, default=None, help="folder on the disk to test (default: a temp dir)")
    ap.add_argument("--ram", action="store_true",
                    help="record into /dev/shm (where it has room): the recorder's own cost, without the disk's")
    ap.add_argument("--no-monitor", action="store_true", help="skip the search with the live monitor")
    args = ap.parse_args()
    frames = sample_frames()
    size = sum(map(len, frames)) / len(frames)
    parent, room = take_folder(args.out, args.ram, size, args.seconds)
    folder = Path(tempfile.mkdtemp(prefix="bench-recorder-", dir=parent))
    runs: list[Run] = []
    try:
        print(f"frames: 1280x720 JPEG, {size / 1e3:.0f} KB mean; cameras keep {BUFFERS} frames; "
              f"{os.cpu_count()} CPUs; takes in {folder} ({file_system(folder)}); {args.runs} runs of "
              f"{args.seconds:g} s takes")
        start = TARGET_CAMERAS
        for k in range(args.runs):
            # the monitor is searched in the first run only: its goal is a ratio of two counts
            # found side by side, and one pair of searches keeps the benchmark to a few minutes
            # a run after the first starts from the count the run before found, and steps up less
            run = one_run(frames, folder, args, start, 1.5 if k == 0 else 1.2, monitor=k == 0 and not args.no_monitor,
                          room=room)
            runs.append(run)
            best = run.good * args.fps
            print(f"run {k + 1}: plain append {run.cached:.0f} frames/s ({run.cached * size / 1e9:.2f} GB/s; with "
                  f"fsync {run.synced:.0f}); recorder, zero drops: {best:.0f} frames/s = {run.good} cameras x "
                  f"{args.fps:g} FPS ({best * size / 1e9:.2f} GB/s): {best / run.cached:.0%} of the plain append")
            start = run.good or TARGET_CAMERAS
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    ratios = [r.good * args.fps / r.cached for r in runs]
    print(f"over {len(runs)} runs, min / median / max:")
    print(f"  plain file append (one thread, one file; best of each run's baselines): "
          f"{spread([r.cached for r in runs], '.0f')} frames/s; with fsync {spread([r.synced for r in runs], '.0f')}")
    print(f"  recorder, zero drops: {spread([r.good for r in runs], '.0f')} cameras x {args.fps:g} FPS "
          f"= {spread([r.good * args.fps for r in runs], '.0f')} frames/s")
    print(f"  recorder / plain append: {spread(ratios, '.0%')} (goal >= {GOAL:.0%} in every run: "
          f"{'met' if min(ratios) >= GOAL else 'NOT met'})")
    need = TARGET_CAMERAS * TARGET_FPS
    worst = min(r.good for r in runs) * args.fps
    if worst >= need:
        print(f"{TARGET_CAMERAS} cameras x {TARGET_FPS:g} FPS ({need:.0f} frames/s) fit on this machine in every run")
    else:
        print(f"{TARGET_CAMERAS} cameras x {TARGET_FPS:g} FPS ({need:.0f} frames/s) do NOT fit on this machine in "
              f"every run; the worst run recorded {int(worst // TARGET_FPS)} cameras at {TARGET_FPS:g} FPS, or "
              f"{TARGET_CAMERAS} cameras at {worst / TARGET_CAMERAS:.0f} FPS")
    first = runs[0]
    if first.watched is not None:
        ratio = first.watched / first.good if first.good else float(first.watched == 0)
        print(f"with the monitor and a page polling every {POLL_S:g} s (run 1): {first.watched} cameras x "
              f"{args.fps:g} FPS with zero drops, without: {first.good}; {ratio:.0%} (goal >= {MONITOR_GOAL:.0%})")


if __name__ == "__main__":
    main()
