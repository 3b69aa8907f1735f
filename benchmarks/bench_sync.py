"""Sync accuracy and speed: a 53-camera simulated take against its ground truth, side by side.

    .venv/bin/python benchmarks/bench_sync.py [--seconds 60] [--cameras 53] [--lp-cameras 16]

Frames come from the simulated cube's clock model (rig.sim.clocks: per camera offset, drift,
timestamp jitter, transfer latency with an exponential tail, drops), the same tables
tests/test_sync.py builds, for a free-running and a hardware-triggered take. On top, the host
stalls now and then (every ~7 s per camera, 30 ms during which arrivals queue up), as a busy
recording machine does. Four ways to put every frame on the host clock are scored:

- ours: dataset_tools.sync (windowed 5 % envelope of arrival - device time, MAD-trimmed line);
- least squares of arrival against device time (np.polyfit), the first thing one would write;
- linear-programming quantile regression at the same 5 % (scipy.optimize.linprog, HiGHS), the
  textbook robust estimator;
- host arrival times as they are (no device clock), what grouping on arrival does.

Each gets the known latency floor subtracted, and the same grouping (dataset_tools.sync.group_frames).
Scores: clock offset and drift error per camera, and per frame group the error of the reported
exposure spread against the true spread of the same frames. One core.
"""

from __future__ import annotations

import os

os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})

import argparse  # noqa: E402
import importlib.util  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from dataset_tools.sync import analyze_sync, fit_clock, group_frames  # noqa: E402
from rig.sim.cube import SimulatedCube  # noqa: E402

_spec = importlib.util.spec_from_file_location("test_sync", REPO / "tests" / "test_sync.py")
test_sync = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(test_sync)

FPS = 120.0
QUANTILE = 0.05


def add_stalls(frames: dict, seed: int = 0, every_s: float = 7.0, stall_ns: int = 30_000_000) -> int:
    """Host stalls: arrivals inside a stall are stamped when it ends (in order, 50 us apart)."""
    rng = np.random.default_rng(seed)
    count = 0
    for table in frames.values():
        h = table["t_host_ns"]
        starts = np.sort(rng.uniform(h[0], h[-1], max(1, int((h[-1] - h[0]) / 1e9 / every_s))))
        for s in starts.astype(np.int64):
            inside = np.flatnonzero((h >= s) & (h < s + stall_ns))
            h[inside] = s + stall_ns + 50_000 * np.arange(inside.size)
            count += 1
    return count


def lp_quantile_fit(d: np.ndarray, h: np.ndarray, q: float) -> tuple[float, float]:
    """(intercept ns, slope) of the q-quantile regression of (h - d) on d, as a linear program."""
    from scipy import sparse
    from scipy.optimize import linprog

    x = (d - d[0]) / 1e9
    y = ((h - h[0]) - (d - d[0])) / 1e3
    n = x.size
    cost = np.concatenate([[0.0, 0.0], np.full(n, q), np.full(n, 1 - q)])
    A = sparse.hstack([sparse.csr_matrix(np.stack([np.ones(n), x], 1)), sparse.identity(n),
                       -sparse.identity(n)]).tocsr()
    res = linprog(cost, A_eq=A, b_eq=y, bounds=[(None, None)] * 2 + [(0, None)] * (2 * n), method="highs")
    return res.x[0] * 1e3, res.x[1] / 1e6


def from_lines(frames: dict, lines: dict, latency: dict, t0: int) -> tuple[list, list, list]:
    """Host mid-exposures, offsets at t0 and drifts (ppm) from fitted lines
    (h - d) = intercept + slope * (d - d0), one (intercept, slope) per camera, floor subtracted."""
    exposure, offset, drift = [], [], []
    for cam, (intercept, slope) in lines.items():
        d, h = frames[cam]["t_device_ns"], frames[cam]["t_host_ns"]
        exposure.append(h[0] + (d - d[0]).astype(np.float64) * (1 + slope) + intercept - latency[cam])
        offset.append(float(d[0] - t0) + (float(t0 - h[0]) + latency[cam] - intercept) / (1 + slope))
        drift.append((1 / (1 + slope) - 1) * 1e6)
    return exposure, offset, drift


def score(name, exposures, frames, truth, t0, offsets=None, drifts=None, true_offset=None, true_drift=None,
          seconds=None) -> dict:
    """Offset/drift errors and the error of every group's reported spread against the truth."""
    g = group_frames(exposures, FPS, t0_ns=t0, cameras=list(frames))
    true = np.full(g.frame_index.shape, np.nan)
    for c, cam in enumerate(frames):
        fi = g.frame_index[:, c]
        true[fi >= 0, c] = truth[c, frames[cam]["seq"][fi[fi >= 0]]]
    true_spread = np.fmax.reduce(true, axis=1) - np.fmin.reduce(true, axis=1)
    both = np.isfinite(g.spread_ns)
    err = np.abs(g.spread_ns[both] - true_spread[both]) / 1e6
    row = {"method": name, "spread_err_p50": np.median(err), "spread_err_p99": np.percentile(err, 99),
           "spread_err_max": err.max(), "spread_true_p50": np.median(true_spread[both]) / 1e6,
           "time_s": seconds}
    if offsets is not None:
        row["offset_err_max"] = np.max(np.abs(np.asarray(offsets) - true_offset)) / 1e6
        row["drift_err_max"] = np.max(np.abs(np.asarray(drifts) - true_drift))
    return row


def run(sync: str, seconds: float, cameras: int, lp_cameras: int) -> None:
    rig = test_sync.sim_rig(cameras, sync)
    cube = SimulatedCube(rig, "calibration", duration_s=seconds)
    frames, truth, dropped = test_sync.clock_frames(cube, int(seconds * FPS))
    stalls = add_stalls(frames)
    latency = {c.id: test_sync.latency_floor_ns(c) for c in rig.cameras}
    true_offset = np.array([c.sim.clock_offset_ms * 1e6 for c in rig.cameras])
    true_drift = np.array([c.sim.drift_ppm for c in rig.cameras])
    rows = sum(t["seq"].size for t in frames.values())
    print(f"\n{sync}: {cameras} cameras x {seconds:g} s at {FPS:g} FPS = {rows} frames received, "
          f"{int(dropped.sum())} dropped, {stalls} host stalls of 30 ms")

    start = time.perf_counter()
    result = analyze_sync(frames, FPS, sync=sync, t0_ns=cube.t0_ns, latency_ns=latency)
    ours_s = time.perf_counter() - start
    found = [c.check.dropped_seq for c in result.cameras]
    missed = false = 0
    for c, cam in enumerate(frames):
        seq = frames[cam]["seq"]
        true_drops = np.flatnonzero(dropped[c])
        true_drops = true_drops[(true_drops > seq.min()) & (true_drops < seq.max())]
        missed += np.setdiff1d(true_drops, found[c]).size
        false += np.setdiff1d(found[c], true_drops).size
    print(f"drops: {sum(f.size for f in found)} found, {missed} missed, {false} false")
    table = [score("ours (5% window envelope)", [c.exposure_ns for c in result.cameras], frames, truth,
                   cube.t0_ns, [c.fit.offset_ns for c in result.cameras],
                   [c.fit.drift_ppm for c in result.cameras], true_offset, true_drift, ours_s)]
    # the envelope fit alone, to compare like with like against the other fits
    start = time.perf_counter()
    for cam, t in frames.items():
        fit_clock(t["t_device_ns"], t["t_host_ns"], latency_ns=latency[cam], t0_ns=cube.t0_ns)
    fit_s = time.perf_counter() - start

    start = time.perf_counter()
    ls = {cam: np.polyfit((t["t_device_ns"] - t["t_device_ns"][0]).astype(float),
                          ((t["t_host_ns"] - t["t_host_ns"][0]) - (t["t_device_ns"] - t["t_device_ns"][0])
                           ).astype(float), 1) for cam, t in frames.items()}
    ls_s = time.perf_counter() - start
    exp, off, dr = from_lines(frames, {cam: (b, a) for cam, (a, b) in ls.items()}, latency, cube.t0_ns)
    table.append(score("least squares (np.polyfit)", exp, frames, truth, cube.t0_ns, off, dr, true_offset,
                       true_drift, ls_s))

    lp_ids = list(frames)[:lp_cameras]
    start = time.perf_counter()
    lp = {cam: lp_quantile_fit(frames[cam]["t_device_ns"], frames[cam]["t_host_ns"], QUANTILE) for cam in lp_ids}
    lp_s = time.perf_counter() - start
    sub = {cam: frames[cam] for cam in lp_ids}
    exp, off, dr = from_lines(sub, lp, latency, cube.t0_ns)
    n = len(lp_ids)
    table.append(score(f"LP quantile regression ({n} cams)", exp, sub, truth[:n], cube.t0_ns,
                       off, dr, true_offset[:n], true_drift[:n], lp_s))
    if n < cameras:
        mine = result.cameras[:n]
        table.append(score(f"ours on the same {n} cams", [c.exposure_ns for c in mine], sub, truth[:n],
                           cube.t0_ns, [c.fit.offset_ns for c in mine], [c.fit.drift_ppm for c in mine],
                           true_offset[:n], true_drift[:n]))

    exp = [t["t_host_ns"].astype(np.float64) - latency[cam] for cam, t in frames.items()]
    table.append(score("host arrival times", exp, frames, truth, cube.t0_ns))

    print(f"{'method':38s} {'offset err':>11s} {'drift err':>10s} {'spread err (ms)':>22s} {'time':>9s}")
    print(f"{'':38s} {'max (ms)':>11s} {'max (ppm)':>10s} {'p50':>7s} {'p99':>7s} {'max':>6s} {'(s)':>9s}")
    for r in table:
        off = f"{r['offset_err_max']:.4f}" if "offset_err_max" in r else "-"
        dr = f"{r['drift_err_max']:.3f}" if "drift_err_max" in r else "-"
        t = f"{r['time_s']:.3f}" if r["time_s"] is not None else "-"
        print(f"{r['method']:38s} {off:>11s} {dr:>10s} {r['spread_err_p50']:7.4f} {r['spread_err_p99']:7.4f} "
              f"{r['spread_err_max']:6.3f} {t:>9s}")
    print(f"true exposure spread, median over groups: {table[0]['spread_true_p50']:.4f} ms")
    per_cam_lp = lp_s / len(lp_ids)
    print(f"time: whole validation (fits, drops, groups) {ours_s:.3f} s; envelope fits alone {fit_s:.3f} s = "
          f"{fit_s / ls_s:.1f}x least squares, LP quantile regression {per_cam_lp * cameras / fit_s:.0f}x slower "
          f"({per_cam_lp:.2f} s per camera)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--cameras", type=int, default=53)
    parser.add_argument("--lp-cameras", type=int, default=16, help="cameras the (slow) LP fit runs on")
    args = parser.parse_args()
    for sync in ("free-run", "hardware-trigger"):
        run(sync, args.seconds, args.cameras, min(args.lp_cameras, args.cameras))


if __name__ == "__main__":
    main()
