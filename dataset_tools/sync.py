"""Sync validation of a recorded take (DESIGN.md: "The stages", 2, and "sync_report.json").

Per camera: a robust fit of the device clock to the host clock, drops from sequence gaps,
duplicate and non-monotonic timestamps, frame-interval statistics. Per take: every camera's
frames assigned to the rig's nominal ticks (the frame groups later stages work on), the real
spread of exposure times within each group, an optical check against LED flashes, a verdict.

Everything below works on plain arrays; `analyze_take` / `sync_take` run it on a take folder
(manus_core.take.Take) and write TAKE/sync_report.json, .md and .png. docs/sync.md explains
the estimator and what every number means.

Times: ns on the host clock (CLOCK_MONOTONIC) unless a name says otherwise.
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from manus_core.errors import SyncError, SyncReportExists

REPORT_VERSION = 1
SYNC_MODES = ("free-run", "software-trigger", "hardware-trigger")


# --------------------------------------------------------------------------------------------
# Clock fit
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ClockFit:
    """Host-clock mid-exposure of a device timestamp d:

        e(d) = h_ref + (d - d_ref) * (1 + slope) + intercept - latency_ns

    `intercept + slope * (d - d_ref)` is the lower envelope of (t_host - t_device): the earliest
    a frame stamped d reaches the host. `latency_ns` is the known floor of mid-exposure -> host
    arrival (half the exposure plus readout and transfer); 0 when nobody said, and then every
    exposure time carries that unknown floor. `offset_ns` is device clock minus host clock at
    host time t0_ns (None when the camera gave no usable device clock).
    """

    d_ref: int
    h_ref: int
    intercept: float
    slope: float
    latency_ns: float
    t0_ns: int
    device_clock: bool
    sigma_ns: float           # scatter of the window envelope points about the line
    x_mean: float             # mean and spread of the windows' device times (ns from d_ref)
    sxx: float
    windows: int              # windows the line went through (inliers)
    residual_ns: float        # median arrival above the envelope: the transfer jitter

    def exposure_ns(self, t_device: np.ndarray) -> np.ndarray:
        """Host-clock mid-exposure (float64 ns) of device timestamps."""
        u = (np.asarray(t_device, np.int64) - self.d_ref).astype(np.float64)
        return self.h_ref + (u * (1.0 + self.slope) + self.intercept - self.latency_ns)

    def at(self, t0_ns: int) -> ClockFit:
        """The same fit with offsets quoted at another host time."""
        return dataclasses.replace(self, t0_ns=int(t0_ns))

    @property
    def drift_ppm(self) -> float:
        return (1.0 / (1.0 + self.slope) - 1.0) * 1e6

    @property
    def drift_se_ppm(self) -> float:
        return self.sigma_ns / math.sqrt(self.sxx) * 1e6 if self.sxx > 0 else math.inf

    @property
    def offset_ns(self) -> float | None:
        if not self.device_clock:
            return None
        # the device timestamp whose exposure lies at t0, minus t0
        return float(self.d_ref - self.t0_ns) + \
            (float(self.t0_ns - self.h_ref) + self.latency_ns - self.intercept) / (1.0 + self.slope)

    @property
    def offset_se_ns(self) -> float:
        """Standard error of the envelope at t0 (host and device time share a scale to 1e-4)."""
        if self.sxx <= 0:
            return math.inf
        x0 = float(self.t0_ns - self.h_ref)
        return self.sigma_ns * math.sqrt(1.0 / self.windows + (x0 - self.x_mean) ** 2 / self.sxx)


def _window_quantile(x: np.ndarray, r: np.ndarray, window: int, q: float) -> tuple[np.ndarray, np.ndarray]:
    """(mean x, q-quantile of r) over consecutive windows of about `window` samples."""
    n = x.size
    nw = max(2, n // window)
    gid = (np.arange(n) * nw) // n
    order = np.lexsort((r, gid))
    counts = np.bincount(gid, minlength=nw)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    picked = order[starts + np.floor(q * (counts - 1)).astype(np.int64)]
    return np.bincount(gid, weights=x, minlength=nw) / counts, r[picked]


def _robust_line(x: np.ndarray, y: np.ndarray, floor: float) -> tuple[float, float, np.ndarray, float]:
    """Least squares with MAD trimming: (intercept at x=0, slope, inlier mask, residual sigma).

    A window whose every frame came late (a host stall, a USB hiccup) lifts its quantile; the
    trimming drops it instead of letting it tilt the line."""
    keep = np.ones(x.size, bool)
    for _ in range(4):
        A = np.stack([np.ones(keep.sum()), x[keep]], 1)
        (a, b), *_ = np.linalg.lstsq(A, y[keep], rcond=None)
        res = y - (a + b * x)
        sigma = max(1.4826 * float(np.median(np.abs(res[keep] - np.median(res[keep])))), floor)
        new = np.abs(res) <= 4.0 * sigma
        if new.sum() < 2 or np.array_equal(new, keep):
            break
        keep = new
    dof = max(int(keep.sum()) - 2, 1)
    sigma = max(float(np.sqrt(np.sum(res[keep] ** 2) / dof)), floor)
    return float(a), float(b), keep, sigma


def fit_clock(t_device: np.ndarray, t_host: np.ndarray, *, latency_ns: float = 0.0,
              t0_ns: int | None = None, quantile: float = 0.05, window: int = 64,
              has_device_clock: bool = True) -> ClockFit:
    """Fit host arrival against device time on a low-quantile envelope.

    Arrival = exposure + floor + a one-sided transfer tail, so least squares would put the line
    through the mean latency and tilt with every burst of late frames. Instead the frames are cut
    into consecutive windows of about `window` frames; in each the `quantile` (default 5 %) of
    (t_host - t_device), after removing the current slope, is the window's envelope point; a
    MAD-trimmed line through those points gives intercept and slope; three rounds settle the
    slope. The 5 % quantile is biased above the true floor by that quantile of the transfer
    jitter (15 us for an exponential tail of 0.3 ms) and is far less sensitive than the minimum
    to a single early host stamp or device-timestamp noise.
    """
    d = np.asarray(t_device, np.int64)
    h = np.asarray(t_host, np.int64)
    if d.size == 0:
        raise SyncError("no frames to fit a clock to")
    d_ref, h_ref = int(d[0]), int(h[0])
    u = (d - d_ref).astype(np.float64)
    v = ((h - h_ref) - (d - d_ref)).astype(np.float64)
    if d.size < 4 or np.ptp(u) <= 0:
        # too few frames for a slope: the envelope is the earliest arrival
        a, b, sigma, x_mean, sxx, inliers = float(v.min()), 0.0, math.inf, 0.0, 0.0, 1
    else:
        window = int(min(window, max(4, d.size // 6)))
        b = 0.0
        for _ in range(3):
            xm, qv = _window_quantile(u, v - b * u, window, quantile)
            a, db, keep, sigma = _robust_line(xm, qv, floor=1.0)
            b += db
        xk = xm[keep]
        x_mean, sxx, inliers = float(xk.mean()), float(np.sum((xk - xk.mean()) ** 2)), int(keep.sum())
    residual = float(np.median(v - (a + b * u)))
    return ClockFit(d_ref, h_ref, float(a), float(b), float(latency_ns), h_ref if t0_ns is None else int(t0_ns),
                    has_device_clock, float(sigma), x_mean, sxx, inliers, residual)


# --------------------------------------------------------------------------------------------
# Sequence numbers and timestamps
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class SequenceCheck:
    """What the sequence numbers and timestamps of one camera's rows say.

    `order` lists the usable rows (indices into the camera's rows, frames.csv order) by sequence
    number; rows left out repeat a sequence number or are not later than their predecessor."""

    order: np.ndarray
    dropped_seq: np.ndarray
    discontinuities: int          # sequence jumps too large to be drops (counter reset or wrap)
    duplicate_seq: int
    reordered_seq: int            # rows whose seq is below one seen before (out of arrival order)
    duplicate_device_ts: int
    backwards_device_ts: int
    backwards_host_ts: int


def check_sequence(seq: np.ndarray, t_device: np.ndarray, t_host: np.ndarray,
                   max_gap: int | None = None) -> SequenceCheck:
    """Drops from sequence gaps; duplicate and non-monotonic timestamps.

    A gap larger than `max_gap` (default: max(1000, rows)) is a discontinuity, not that many drops.
    Frames lost before the first or after the last received one leave no gap and are not seen.
    """
    seq = np.asarray(seq, np.int64)
    d = np.asarray(t_device, np.int64)
    h = np.asarray(t_host, np.int64)
    n = seq.size
    if n == 0:
        empty = np.zeros(0, np.int64)
        return SequenceCheck(empty, empty, 0, 0, 0, 0, 0, 0)
    prev_max = np.maximum.accumulate(np.concatenate([[np.iinfo(np.int64).min], seq[:-1]]))
    reordered = int(np.count_nonzero(seq < prev_max))
    order = np.argsort(seq, kind="stable")
    first = np.concatenate([[True], np.diff(seq[order]) != 0])
    duplicate_seq = int(n - first.sum())
    order = order[first]
    # a frame with a bad timestamp was still received: gaps come from every distinct seq
    s = seq[order]
    gaps = np.diff(s) - 1
    max_gap = max(1000, n) if max_gap is None else max_gap
    discontinuities = int(np.count_nonzero(gaps > max_gap))
    gaps = np.where(gaps > max_gap, 0, gaps)
    start = np.repeat(s[:-1], gaps)
    within = np.arange(start.size) - np.repeat(np.cumsum(gaps) - gaps, gaps)
    dropped = start + within + 1
    dd = np.diff(d[order])
    duplicate_dev = int(np.count_nonzero(dd == 0))
    backwards_dev = int(np.count_nonzero(dd < 0))
    # a row not later than the last good one is left out; its neighbours stay usable
    good_so_far = np.maximum.accumulate(d[order])
    order = order[np.concatenate([[True], d[order][1:] > good_so_far[:-1]])]
    backwards_host = int(np.count_nonzero(np.diff(h) < 0))
    return SequenceCheck(order, dropped, discontinuities, duplicate_seq, reordered, duplicate_dev,
                         backwards_dev, backwards_host)


# --------------------------------------------------------------------------------------------
# One camera
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class CameraSync:
    """One camera's validation. `exposure_ns` (rows,) is the host-clock mid-exposure of every row
    (NaN for rows left out); the interval statistics are over device-time intervals per sequence
    step (host arrival intervals for a camera without a device clock)."""

    id: str
    seq: np.ndarray
    check: SequenceCheck
    fit: ClockFit | None
    exposure_ns: np.ndarray
    interval_mean_ns: float
    interval_std_ns: float
    device_clock: bool
    latency_known: bool

    @property
    def rows(self) -> int:
        return int(self.seq.size)


def _has_device_clock(d: np.ndarray, seq: np.ndarray) -> bool:
    """A device clock worth fitting: it moves forward between most consecutive frames."""
    if d.size < 2:
        return bool(d.size and d[0] != 0)
    order = np.argsort(seq, kind="stable")
    return float(np.mean(np.diff(d[order]) > 0)) > 0.5


def analyze_camera(cam: str, seq: np.ndarray, t_device: np.ndarray, t_host: np.ndarray, fps: float, *,
                   latency_ns: float | None = None, t0_ns: int | None = None) -> CameraSync:
    """Sequence check, clock fit and interval statistics of one camera's rows (frames.csv order).

    A camera without device timestamps (all zero, or not increasing) is fitted on its sequence
    numbers instead, at the nominal period: its exposures then follow a steady frame rate and its
    offset is unknown."""
    seq = np.asarray(seq, np.int64)
    d = np.asarray(t_device, np.int64)
    h = np.asarray(t_host, np.int64)
    period = 1e9 / fps
    device_clock = _has_device_clock(d, seq)
    if not device_clock:
        d = np.rint(seq * period).astype(np.int64)
    check = check_sequence(seq, d, h)
    exposure = np.full(seq.size, np.nan)
    if check.order.size == 0:
        return CameraSync(cam, seq, check, None, exposure, math.nan, math.nan, device_clock,
                          latency_ns is not None)
    o = check.order
    fit = fit_clock(d[o], h[o], latency_ns=latency_ns or 0.0, t0_ns=t0_ns, has_device_clock=device_clock)
    exposure[o] = fit.exposure_ns(d[o])
    steps = np.diff(seq[o])
    # without a device clock only the arrivals say how steady the frames came
    stamps = d[o] if device_clock else h[o]
    intervals = np.diff(stamps) / np.maximum(steps, 1)
    intervals = intervals[steps < max(1000, seq.size)]
    mean = float(intervals.mean()) if intervals.size else math.nan
    std = float(intervals.std()) if intervals.size > 1 else math.nan
    return CameraSync(cam, seq, check, fit, exposure, mean, std, device_clock, latency_ns is not None)


# --------------------------------------------------------------------------------------------
# Frame groups
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class FrameGroups:
    """Frames of every camera on the rig's nominal ticks.

    frame_index (T,C): the camera's frame index (its row of frames.csv) in group t, -1 where it has
    none; frame_ns (T,): the group's tick on the host clock; exposure_ns (T,C): the estimated
    host-clock mid-exposure of each member (NaN where none); tick (T,): tick numbers counted from
    t0_ns; phase_ns: where in the period the groups are centred (relative to t0_ns + k * period).
    """

    cameras: tuple[str, ...]
    frame_index: np.ndarray
    frame_ns: np.ndarray
    exposure_ns: np.ndarray
    tick: np.ndarray
    t0_ns: int
    period_ns: float
    phase_ns: float
    camera_phase_ns: np.ndarray     # (C,) each camera's mean exposure time minus its group's tick
    unassigned: np.ndarray          # (C,) frames that lost their tick to a nearer frame of the camera

    @property
    def spread_ns(self) -> np.ndarray:
        """(T,) max - min estimated exposure within each group; NaN for groups of fewer than 2."""
        members = np.count_nonzero(self.frame_index >= 0, axis=1)
        spread = np.fmax.reduce(self.exposure_ns, axis=1) - np.fmin.reduce(self.exposure_ns, axis=1)
        return np.where(members >= 2, spread, np.nan)


def _circular_phase(phase: np.ndarray, period: float) -> float:
    """Mean of phases on the circle of one period, in [0, period)."""
    angle = np.angle(np.mean(np.exp(2j * np.pi * phase / period)))
    return float((angle / (2 * np.pi) * period) % period)


def _phase_gaps(exposure_ns: np.ndarray, period_ns: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row of (T,C) times: phases sorted on the circle of one period, the gap after each
    (wrapping round), and how many are present (NaN = absent; it repeats a present phase, and a
    zero gap changes nothing)."""
    e = np.atleast_2d(np.asarray(exposure_ns, np.float64))
    count = np.count_nonzero(np.isfinite(e), axis=1)
    fill = np.fmax.reduce(e, axis=1)[:, None]
    p = np.sort(np.where(np.isfinite(e), e, fill) % period_ns, axis=1)
    gaps = np.diff(np.concatenate([p, p[:, :1] + period_ns], axis=1), axis=1)
    return p, gaps, count


def _group_centre(phases: np.ndarray, period: float) -> float:
    """The tick phase whose group boundary (centre + period/2) falls in the widest gap between
    the cameras' phases, so no camera's frames straddle a boundary if the phases allow it."""
    if not np.isfinite(phases).any():
        return 0.0
    p, gaps, _ = _phase_gaps(phases, period)
    i = int(np.argmax(gaps[0]))
    return float((p[0, i] + gaps[0, i] / 2 + period / 2) % period)


def spread_floor_ns(exposure_ns: np.ndarray, period_ns: float) -> np.ndarray | float:
    """The smallest spread exposures with these phases can have in any grouping: the period minus
    the widest gap between their phases on the circle. `exposure_ns` (C,) gives a float, (T,C)
    one value per row (NaN = no frame; NaN for rows of fewer than two)."""
    _, gaps, count = _phase_gaps(exposure_ns, period_ns)
    floor = np.where(count >= 2, period_ns - gaps.max(axis=1), np.nan)
    return float(floor[0]) if np.ndim(exposure_ns) == 1 else floor


def group_frames(exposure_ns: Sequence[np.ndarray], fps: float, *, t0_ns: int | None = None,
                 cameras: Sequence[str] | None = None) -> FrameGroups:
    """Assign every camera's frames (host-clock mid-exposures, NaN = unusable) to nominal ticks.

    Ticks are t0 + phase + k * period. The phase puts the group boundaries in the widest gap of the
    cameras' exposure phases (for triggered cameras: opposite their common phase; for free-running
    ones: where it splits the fewest cameras). Each frame goes to its nearest tick; when two frames
    of one camera land on one tick (its clock runs fast, a timestamp glitch) the nearer one stays.
    """
    period = 1e9 / fps
    exposure_ns = [np.asarray(e, np.float64) for e in exposure_ns]
    cams = tuple(cameras) if cameras is not None else tuple(str(i) for i in range(len(exposure_ns)))
    finite = [e[np.isfinite(e)] for e in exposure_ns]
    if t0_ns is None:
        firsts = [f.min() for f in finite if f.size]
        t0_ns = int(math.floor(min(firsts))) if firsts else 0
    cam_phase = np.array([_circular_phase(f - t0_ns, period) if f.size else np.nan for f in finite])
    centre = _group_centre(cam_phase, period)
    if centre > period / 2:
        centre -= period
    ticks, unassigned = [], np.zeros(len(exposure_ns), np.int64)
    for e in exposure_ns:
        rows = np.flatnonzero(np.isfinite(e))
        rel = (e[rows] - t0_ns - centre) / period
        k = np.rint(rel).astype(np.int64)
        order = np.lexsort((np.abs(rel - k), k))
        first = np.concatenate([[True], np.diff(k[order]) != 0])[:order.size]
        unassigned[len(ticks)] = int(order.size - first.sum())
        ticks.append((k[order][first], rows[order][first]))
    all_k = np.concatenate([k for k, _ in ticks]) if ticks else np.zeros(0, np.int64)
    if all_k.size == 0:
        kmin, count = 0, 0
    else:
        kmin, count = int(all_k.min()), int(all_k.max() - all_k.min() + 1)
    frame_index = np.full((count, len(exposure_ns)), -1, np.int64)
    exposure = np.full((count, len(exposure_ns)), np.nan)
    for c, (k, rows) in enumerate(ticks):
        frame_index[k - kmin, c] = rows
        exposure[k - kmin, c] = exposure_ns[c][rows]
    tick = np.arange(kmin, kmin + count, dtype=np.int64)
    frame_ns = np.rint(t0_ns + centre + tick * period).astype(np.int64)
    cam_phase_rel = (cam_phase - centre + period / 2) % period - period / 2
    return FrameGroups(cams, frame_index, frame_ns, exposure, tick, int(t0_ns), period, float(centre),
                       cam_phase_rel, unassigned)


# --------------------------------------------------------------------------------------------
# LED flashes and the optical check
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Flash:
    """An LED flash from the command log: it started somewhere in [on_lo_ns, on_hi_ns] (sent ..
    acknowledged) and lasted duration_ns (timed by the controller)."""

    on_lo_ns: int
    on_hi_ns: int
    duration_ns: int
    level: float

    @property
    def on_ns(self) -> float:
        return (self.on_lo_ns + self.on_hi_ns) / 2


def led_flashes(log: Iterable[Mapping]) -> list[Flash]:
    """The flashes of a take.json LED log (rig.leds records: ASCII `FLASH` with args [ms, level
    0..1000] acknowledged `ok`, or DMX `FLASH` with `ms` and `levels`, status `sent`)."""
    out = []
    for rec in log:
        if not isinstance(rec, Mapping) or rec.get("cmd") != "FLASH" or rec.get("status") not in ("ok", "sent"):
            continue
        sent = rec.get("t_send_ns")
        done = rec.get("t_ack_ns") or rec.get("t_done_ns") or sent
        args = rec.get("args") or []
        ms = rec.get("ms", args[0] if args else None)
        if not isinstance(sent, int) or not isinstance(done, int) or not isinstance(ms, (int, float)):
            continue
        if "levels" in rec and rec["levels"]:
            level = float(max(rec["levels"]))
        else:
            level = float(args[1]) / 1000 if len(args) > 1 else 1.0
        out.append(Flash(int(sent), int(done), int(round(ms * 1e6)), level))
    return sorted(out, key=lambda f: f.on_lo_ns)


BrightnessFn = Callable[[str, np.ndarray], np.ndarray]
"""brightness(cam, frame_indices (sorted, unique)) -> mean image brightness (n,) of those frames."""


def _onset_bounds(e: np.ndarray, lit: np.ndarray, idx: np.ndarray, lo_ns: float, hi_ns: float,
                  rising: bool) -> tuple[int, float, float] | None:
    """The frame where `lit` switches (first rise or last fall in `idx` order) and the bounds it
    puts on the timing error delta = true exposure - estimated exposure."""
    contiguous = np.diff(idx) == 1
    if rising:
        j = np.flatnonzero(lit[1:] & ~lit[:-1] & contiguous)
        if j.size == 0:
            return None
        after, before = idx[j[0] + 1], idx[j[0]]
        # e_after + delta >= t_on >= lo, e_before + delta < t_on <= hi
        return int(after), lo_ns - e[after], hi_ns - e[before]
    j = np.flatnonzero(~lit[1:] & lit[:-1] & contiguous)
    if j.size == 0:
        return None
    last, nxt = idx[j[-1]], idx[j[-1] + 1]
    return int(last), lo_ns - e[nxt], hi_ns - e[last]


def optical_check(cameras: Sequence[CameraSync], flashes: Sequence[Flash], brightness: BrightnessFn, *,
                  t0_ns: int = 0, margin_frames: int = 4, min_contrast: float = 2.0,
                  progress: Callable[[int], None] | None = None) -> dict:
    """Find each flash's onset (and end) in every camera's images and compare with the timestamps.

    Only frames within `margin_frames` of where the timestamps put the flash's edges are decoded.
    A frame counts as lit above halfway between the darkest and brightest of them (a bright flash
    over a dimmer set-point). The first lit frame bounds the camera's timing error delta (true minus
    timestamp-predicted exposure): e[first] + delta >= flash start and e[previous] + delta < flash
    start, with the flash start only known to lie between the command's send and acknowledgement;
    the end of the flash bounds it the same way. The bounds of all flashes are intersected.
    """
    out: dict = {"flashes": [{"on_ms": round((f.on_ns - t0_ns) / 1e6, 4), "duration_ms": f.duration_ns / 1e6,
                              "on_uncertainty_ms": (f.on_hi_ns - f.on_lo_ns) / 1e6} for f in flashes],
                 "cameras": {}}
    for cam in cameras:
        e = cam.exposure_ns
        ok = np.flatnonzero(np.isfinite(e))
        entry: dict = {"flashes_seen": 0, "onset_frames": [], "exposure_error_ms": None, "consistent": None,
                       "measured_offset_ms": None, "predicted_offset_ms": None, "error_ms": None}
        out["cameras"][cam.id] = entry
        if ok.size < 2 or cam.fit is None:
            if progress:
                progress(1)
            continue
        period = max(cam.interval_mean_ns, 1.0) if np.isfinite(cam.interval_mean_ns) else 1e7
        margin = margin_frames + int(math.ceil(max((f.on_hi_ns - f.on_lo_ns) for f in flashes) / period)) \
            if flashes else margin_frames
        windows = []
        for f in flashes:
            k_on = int(np.searchsorted(e[ok], f.on_ns))
            k_off = int(np.searchsorted(e[ok], f.on_ns + f.duration_ns))
            sel = np.unique(np.clip(np.concatenate([np.arange(k_on - margin, k_on + margin + 1),
                                                    np.arange(k_off - margin, k_off + margin + 1)]),
                                    0, ok.size - 1))
            windows.append((k_on, ok[sel]))
        wanted = np.unique(np.concatenate([w for _, w in windows])) if windows else np.zeros(0, np.int64)
        values = np.asarray(brightness(cam.id, wanted), np.float64) if wanted.size else np.zeros(0)
        level = dict(zip(wanted.tolist(), values.tolist()))
        lo_delta, hi_delta = -math.inf, math.inf
        for f, (k_on, idx) in zip(flashes, windows):
            b = np.array([level[i] for i in idx.tolist()])
            if b.size < 3 or b.max() - b.min() < min_contrast:
                entry["onset_frames"].append({"predicted": int(ok[min(k_on, ok.size - 1)]), "measured": None})
                continue
            lit = b > (b.max() + b.min()) / 2
            rise = _onset_bounds(e, lit, idx, f.on_lo_ns, f.on_hi_ns, rising=True)
            fall = _onset_bounds(e, lit, idx, f.on_lo_ns + f.duration_ns, f.on_hi_ns + f.duration_ns,
                                 rising=False)
            entry["onset_frames"].append({"predicted": int(ok[min(k_on, ok.size - 1)]),
                                          "measured": None if rise is None else rise[0]})
            for bound in (rise, fall):
                if bound is not None:
                    lo_delta, hi_delta = max(lo_delta, bound[1]), min(hi_delta, bound[2])
            entry["flashes_seen"] += rise is not None
        if np.isfinite(lo_delta) and np.isfinite(hi_delta):
            entry["exposure_error_ms"] = [round(lo_delta / 1e6, 4), round(hi_delta / 1e6, 4)]
            entry["consistent"] = bool(lo_delta <= hi_delta)
            if entry["consistent"]:
                # zero inside the bounds: the timestamps agree with what the images show
                entry["error_ms"] = round(max(lo_delta, 0.0, -hi_delta) / 1e6, 4)
            if cam.fit.offset_ns is not None and entry["consistent"]:
                scale = 1.0 + cam.fit.drift_ppm * 1e-6
                # a later true exposure means a smaller device-minus-host offset
                entry["measured_offset_ms"] = [round((cam.fit.offset_ns - hi_delta * scale) / 1e6, 4),
                                               round((cam.fit.offset_ns - lo_delta * scale) / 1e6, 4)]
                entry["predicted_offset_ms"] = round(cam.fit.offset_ns / 1e6, 4)
        if progress:
            progress(1)
    return out


# --------------------------------------------------------------------------------------------
# The whole take
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class SyncSettings:
    tolerance_ms: float = 3.0        # exposures of a group should lie within this (p95)
    max_drop_pct: float = 1.0        # per camera
    optical_tolerance_ms: float = 1.0


@dataclass(frozen=True)
class SyncResult:
    fps: float
    sync: str
    t0_ns: int
    cameras: tuple[CameraSync, ...]
    groups: FrameGroups
    settings: SyncSettings = field(default_factory=SyncSettings)


def analyze_sync(frames: Mapping[str, Mapping[str, np.ndarray]], fps: float, *, sync: str = "free-run",
                 t0_ns: int | None = None, latency_ns: Mapping[str, float] | None = None,
                 settings: SyncSettings | None = None) -> SyncResult:
    """Validate the frames of a take given as arrays: {cam: {seq, t_device_ns, t_host_ns}} (rows in
    arrival order, as in frames.csv). `latency_ns`: per camera, mid-exposure -> earliest host
    arrival, where known. `t0_ns`: the take's tick 0 (default: the first estimated exposure)."""
    if not fps or fps <= 0:
        raise SyncError(f"fps must be positive, got {fps!r}")
    if sync not in SYNC_MODES:
        raise SyncError(f"unknown sync mode {sync!r} (known: {', '.join(SYNC_MODES)})")
    latency_ns = latency_ns or {}
    cams = []
    for cam, table in frames.items():
        missing = [k for k in ("seq", "t_device_ns", "t_host_ns") if k not in table]
        if missing:
            raise SyncError(f"camera {cam}: missing column(s) {', '.join(missing)}")
        cams.append(analyze_camera(cam, table["seq"], table["t_device_ns"], table["t_host_ns"], fps,
                                   latency_ns=latency_ns.get(cam), t0_ns=t0_ns))
    groups = group_frames([c.exposure_ns for c in cams], fps, t0_ns=t0_ns, cameras=[c.id for c in cams])
    if t0_ns is None:
        # offsets are quoted at t0, which was only known once exposures were
        t0_ns = groups.t0_ns
        cams = [dataclasses.replace(c, fit=c.fit.at(t0_ns)) if c.fit else c for c in cams]
    return SyncResult(float(fps), sync, int(t0_ns), tuple(cams), groups, settings or SyncSettings())


def noise_range_ns(sigma_ns: float, n: int) -> float:
    """Expected max - min of n exposures that coincide but are stamped with N(0, sigma) noise:
    the spread timestamp noise alone shows (sigma * 2.85 for 8 cameras, * 4.6 for 53)."""
    from scipy.special import ndtr

    if n < 2 or not np.isfinite(sigma_ns):
        return 0.0
    x = np.linspace(-9.0, 9.0, 3601)
    cdf = ndtr(x)
    return float(sigma_ns * np.sum(1.0 - cdf ** n - (1.0 - cdf) ** n) * (x[1] - x[0]))


def _r(x: float | None, digits: int = 4) -> float | None:
    return None if x is None or not np.isfinite(x) else round(float(x), digits)


def _stats(values: np.ndarray) -> dict:
    v = values[np.isfinite(values)]
    if v.size == 0:
        return {"median": None, "p95": None, "p99": None, "max": None}
    return {"median": _r(np.median(v)), "p95": _r(np.percentile(v, 95)), "p99": _r(np.percentile(v, 99)),
            "max": _r(v.max())}


def build_report(result: SyncResult, optical: dict | None = None, take: str | None = None) -> dict:
    """sync_report.json (DESIGN.md) from a SyncResult and an optional optical check."""
    s = result.settings
    g = result.groups
    period = g.period_ns
    reasons: list[str] = []
    notes: list[str] = []
    cameras = {}
    for c, cam in enumerate(result.cameras):
        ch, fit = cam.check, cam.fit
        span = cam.rows - ch.duplicate_seq + int(ch.dropped_seq.size)
        drop_pct = 100.0 * ch.dropped_seq.size / span if span else 0.0
        cameras[cam.id] = {
            "frames_received": cam.rows,
            "frames_dropped": int(ch.dropped_seq.size),
            "dropped_seq": ch.dropped_seq.tolist(),
            "clock_offset_ms": _r(fit.offset_ns / 1e6) if fit and fit.offset_ns is not None else None,
            "drift_ppm": _r(fit.drift_ppm, 3) if fit else None,
            "interval_std_ms": _r(cam.interval_std_ns / 1e6),
            "offset_se_ms": _r(fit.offset_se_ns / 1e6) if fit else None,
            "drift_se_ppm": _r(fit.drift_se_ppm, 3) if fit else None,
            "residual_ms": _r(fit.residual_ns / 1e6) if fit else None,
            "latency_floor_ms": _r(fit.latency_ns / 1e6) if fit and cam.latency_known else None,
            "phase_ms": _r(g.camera_phase_ns[c] / 1e6),
            # device-clock intervals are long by the drift; host arrival intervals are not
            "fps_measured": _r(1e9 / cam.interval_mean_ns * (1 + fit.drift_ppm * 1e-6 if cam.device_clock else 1.0), 3)
            if fit and cam.interval_mean_ns > 0 else None,
            "duplicate_seq": ch.duplicate_seq,
            "reordered_seq": ch.reordered_seq,
            "seq_discontinuities": ch.discontinuities,
            "duplicate_timestamps": ch.duplicate_device_ts,
            "nonmonotonic_timestamps": ch.backwards_device_ts,
            "host_backwards": ch.backwards_host_ts,
            "unassigned_frames": int(g.unassigned[c]),
            "device_clock": cam.device_clock,
        }
        if cam.rows == 0 or fit is None:
            reasons.append(f"{cam.id}: no usable frames")
            continue
        bad = [f"{n} {what}" for n, what in ((ch.duplicate_seq, "repeated sequence numbers"),
                                              (ch.duplicate_device_ts, "duplicate device timestamps"),
                                              (ch.backwards_device_ts, "device timestamps going backwards"),
                                              (ch.backwards_host_ts, "host timestamps going backwards"),
                                              (ch.discontinuities, "sequence discontinuities")) if n]
        if bad:
            reasons.append(f"{cam.id}: {', '.join(bad)}")
        if drop_pct > s.max_drop_pct:
            reasons.append(f"{cam.id}: {drop_pct:.2f}% of frames dropped (limit {s.max_drop_pct:g}%)")
        if not cam.device_clock:
            notes.append(f"{cam.id}: no device timestamps; exposures assumed at a steady rate from the "
                         "sequence numbers")
        if abs(fit.drift_ppm) > 1000:
            reasons.append(f"{cam.id}: device clock runs {fit.drift_ppm:.0f} ppm off the host's "
                           "(timestamps in another unit?)")
    spread = g.spread_ns / 1e6
    members = np.count_nonzero(g.frame_index >= 0, axis=1)
    valid = spread[np.isfinite(spread)]
    within = 100.0 * np.count_nonzero(valid <= s.tolerance_ms) / valid.size if valid.size else None
    stats = _stats(spread)
    floor_t = spread_floor_ns(g.exposure_ns - g.t0_ns, period)
    floor = float(np.nanmedian(floor_t)) / 1e6 if np.isfinite(floor_t).any() else math.nan
    if stats["p95"] is not None and stats["p95"] > s.tolerance_ms:
        why = f"exposure spread p95 {stats['p95']:.2f} ms > {s.tolerance_ms:g} ms"
        if result.sync == "free-run":
            why += (f": free-running cameras, whose frame phases alone keep exposures {floor:.2f} ms apart "
                    "(trigger the cameras to do better)")
        reasons.append(why)
    if result.sync == "free-run" and len(result.cameras) > 1:
        notes.append(f"free-run: the cameras' frame phases span {floor:.3f} ms (median over groups), so no "
                     "grouping of these frames can be tighter; the spread reported is what the exposures "
                     "really are")
    latency_known = all(c.latency_known for c in result.cameras)
    if not latency_known:
        notes.append("the transfer latency floor (mid-exposure -> host arrival) is not given for every "
                     "camera: clock offsets are device minus earliest host arrival, and exposure times "
                     "carry each camera's floor (cameras whose floors differ look that much apart)")
    fits = [c.fit for c in result.cameras if c.fit is not None]
    # consecutive intervals differ by two timestamps' noise (and, triggered, two exposures' jitter)
    jitter = [c.interval_std_ns / math.sqrt(2) for c in result.cameras if np.isfinite(c.interval_std_ns)]
    noise = noise_range_ns(float(np.median(jitter)) if jitter else math.nan,
                           int(np.median(members)) if members.size else 0) / 1e6
    timing = {
        "latency_floor_known": latency_known,
        "fit_se_ms": _r(max((f.offset_se_ns for f in fits), default=math.nan) / 1e6),
        "timestamp_jitter_ms": _r(max(jitter, default=math.nan) / 1e6),
        "transfer_jitter_ms": _r(max((f.residual_ns for f in fits), default=math.nan) / 1e6),
        "spread_noise_ms": _r(noise),
    }
    if result.sync != "free-run" and stats["median"] is not None and stats["median"] <= 1.5 * noise:
        notes.append(f"{result.sync}: the median spread {stats['median']:.3f} ms is what timestamp noise "
                     f"alone shows ({noise:.3f} ms): the exposures are at least this close")
    if optical is not None:
        entries = optical["cameras"]
        seen = [cam for cam, e in entries.items() if e["flashes_seen"]]
        for cam, entry in entries.items():
            if entry["consistent"] is False:
                reasons.append(f"optical check: {cam}: the flashes put its exposures at times that exclude "
                               "each other (timestamps that jump, or a flash misread)")
            elif entry["error_ms"] is not None and entry["error_ms"] > s.optical_tolerance_ms:
                lo, hi = entry["exposure_error_ms"]
                reasons.append(f"optical check: {cam}: true exposures lie {lo:+.2f}..{hi:+.2f} ms from where "
                               "its timestamps put them")
            elif seen and not entry["flashes_seen"] and cameras[cam]["frames_received"]:
                reasons.append(f"optical check: {cam}: saw none of the flashes {len(seen)} other cameras saw "
                               "where its timestamps put them")
        if optical["flashes"] and not seen:
            notes.append("optical check: no camera saw a flash (scene too dark, or the LEDs were not in view)")
    return {
        "version": REPORT_VERSION,
        "take": take,
        "fps": result.fps,
        "sync": result.sync,
        "t0_ns": result.t0_ns,
        "cameras": cameras,
        "groups": int(g.frame_index.shape[0]),
        "complete_groups": int(np.count_nonzero(members == len(result.cameras))),
        "spread_ms": stats,
        "within_3ms_pct": _r(within, 3),
        "spread_floor_ms": _r(floor),
        "timing": timing,
        "optical_check": optical,
        "verdict": "pass" if not reasons else "fail",
        "reasons": reasons,
        "notes": notes,
        "settings": {"tolerance_ms": s.tolerance_ms, "max_drop_pct": s.max_drop_pct,
                     "optical_tolerance_ms": s.optical_tolerance_ms},
    }


# --------------------------------------------------------------------------------------------
# Take folders
# --------------------------------------------------------------------------------------------

def _take_latency(meta: Mapping, cams: Sequence[str]) -> dict[str, float]:
    """Per camera latency floor from take.json camera objects: exposure_us / 2 + latency_ms (end of
    exposure -> earliest host arrival), where latency_ms is given (at the top or in "sim")."""
    out = {}
    for entry in meta.get("cameras", []):
        if not isinstance(entry, Mapping) or str(entry.get("id")) not in cams:
            continue
        lat = entry.get("latency_ms", (entry.get("sim") or {}).get("latency_ms"))
        if isinstance(lat, (int, float)):
            exposure = entry.get("exposure_us")
            half_exposure = float(exposure) * 500 if isinstance(exposure, (int, float)) else 0.0
            out[str(entry["id"])] = float(lat) * 1e6 + half_exposure
    return out


def _take_t0(meta: Mapping) -> int | None:
    for key in ("t0_ns", "start_ns"):
        if isinstance(meta.get(key), int):
            return int(meta[key])
    return None


def take_brightness(take) -> BrightnessFn:
    """Mean brightness of chosen frames of a take: packets are read without decoding and only the
    wanted ones are decoded, at 1/8 scale in grey (JPEG DCT scaling, no full decode)."""
    import cv2

    from manus_core.take import TakeError

    def brightness(cam: str, indices: np.ndarray) -> np.ndarray:
        wanted = {int(i): j for j, i in enumerate(indices)}
        out = np.full(len(indices), np.nan)
        last = max(wanted) if wanted else -1
        for k, packet in enumerate(take.packets(cam)):
            if k > last:
                break
            if k in wanted:
                image = cv2.imdecode(packet, cv2.IMREAD_REDUCED_GRAYSCALE_8)
                if image is None:
                    raise TakeError(f"{take.video_path(cam)}: frame {k} is not a decodable JPEG")
                out[wanted[k]] = float(image.mean())
        return out

    return brightness


def take_flashes(take) -> list[Flash]:
    """The LED flashes of a take: take.json's LED command log ("led_log", or "leds")."""
    log = take.meta.get("led_log", take.meta.get("leds"))
    return led_flashes(log) if isinstance(log, list) else []


def analyze_take(path, *, latency_ns: Mapping[str, float] | None = None, optical: bool = True,
                 settings: SyncSettings | None = None,
                 progress: Callable[[int], None] | None = None) -> tuple[SyncResult, dict]:
    """Run the sync validation on a take folder: (result, sync_report dict). Nothing is written."""
    from manus_core.take import Take

    take = path if isinstance(path, Take) else Take(path)
    meta_path = take.path / "take.json"
    if take.fps is None or take.fps <= 0:
        raise SyncError(f"{meta_path}: fps: missing or not a positive number (the ticks need it)")
    sync = take.meta.get("sync", "free-run")
    if sync not in SYNC_MODES:
        raise SyncError(f"{meta_path}: sync: {sync!r} is not one of {', '.join(SYNC_MODES)}")
    frames = {cam: take.camera_frames(cam) for cam in take.cameras}
    latency = {**_take_latency(take.meta, take.cameras), **(latency_ns or {})}
    result = analyze_sync(frames, take.fps, sync=sync, t0_ns=_take_t0(take.meta), latency_ns=latency,
                          settings=settings)
    flashes = take_flashes(take) if optical else []
    check = None
    if flashes:
        check = optical_check(result.cameras, flashes, take_brightness(take), t0_ns=result.t0_ns,
                              progress=progress)
    return result, build_report(result, check, take=take.path.name)


def frame_groups(path) -> FrameGroups:
    """The frame groups of a take (for annotate): frame_index (T,C) with -1, frame_ns (T,)."""
    result, _ = analyze_take(path, optical=False)
    return result.groups


def report_markdown(report: dict) -> str:
    """sync_report.md: the same numbers for people."""
    lines = [f"# Sync report: {report['take'] or 'take'}", "",
             f"**Verdict: {report['verdict'].upper()}** ({report['sync']}, {report['fps']:g} FPS, "
             f"{len(report['cameras'])} cameras)", ""]
    lines += [f"- {r}" for r in report["reasons"]] + ([""] if report["reasons"] else [])
    sp = report["spread_ms"]
    fmt = (lambda v: "n/a" if v is None else f"{v:.3f}")
    lines += ["## Frame groups", "",
              f"{report['groups']} groups on the nominal ticks, {report['complete_groups']} with every camera.", "",
              "Exposure spread within a group (ms): "
              f"median {fmt(sp['median'])}, p95 {fmt(sp['p95'])}, p99 {fmt(sp['p99'])}, max {fmt(sp['max'])}; "
              f"{fmt(report['within_3ms_pct'])}% of groups within {report['settings']['tolerance_ms']:g} ms. "
              f"Frame phases alone allow no less than {fmt(report['spread_floor_ms'])} ms.", "",
              "## How well the timestamps are known", ""]
    t = report["timing"]
    lines += [f"- latency floor given for every camera: {'yes' if t['latency_floor_known'] else 'no'}",
              f"- clock fit standard error (worst camera): {fmt(t['fit_se_ms'])} ms",
              f"- device timestamp jitter (worst camera, upper bound): {fmt(t['timestamp_jitter_ms'])} ms",
              f"- transfer jitter above the envelope (worst camera, median): {fmt(t['transfer_jitter_ms'])} ms", ""]
    if report["notes"]:
        lines += ["## Notes", ""] + [f"- {n}" for n in report["notes"]] + [""]
    lines += ["## Cameras", "",
              "| camera | frames | dropped | offset ms | drift ppm | interval std ms | phase ms | flags |",
              "|---|---:|---:|---:|---:|---:|---:|---|"]
    for cam, c in report["cameras"].items():
        flags = [f"{k}={c[k]}" for k in ("duplicate_seq", "duplicate_timestamps", "nonmonotonic_timestamps",
                                         "host_backwards", "seq_discontinuities", "unassigned_frames") if c[k]]
        lines.append(f"| {cam} | {c['frames_received']} | {c['frames_dropped']} | {fmt(c['clock_offset_ms'])} | "
                     f"{fmt(c['drift_ppm'])} | {fmt(c['interval_std_ms'])} | {fmt(c['phase_ms'])} | "
                     f"{' '.join(flags)} |")
    opt = report["optical_check"]
    if opt:
        lines += ["", "## Optical check", "",
                  f"{len(opt['flashes'])} LED flashes. Exposure error = true minus timestamp-predicted "
                  "mid-exposure, as bounded by the frames where each flash starts and ends.", "",
                  "| camera | flashes seen | exposure error ms | measured offset ms | predicted offset ms |",
                  "|---|---:|---|---|---:|"]
        for cam, c in opt["cameras"].items():
            err, mo = c["exposure_error_ms"], c["measured_offset_ms"]
            err = "n/a" if err is None else f"{err[0]:+.3f} .. {err[1]:+.3f}"
            mo = "n/a" if mo is None else f"{mo[0]:.3f} .. {mo[1]:.3f}"
            lines.append(f"| {cam} | {c['flashes_seen']} | {err} | {mo} | {fmt(c['predicted_offset_ms'])} |")
    return "\n".join(lines) + "\n"


def timeline_png(result: SyncResult, flashes: Sequence[Flash] = (), max_points: int = 4000) -> bytes:
    """A PNG: each camera's exposure offset from its group's tick over time, with drops marked."""
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    g = result.groups
    n = len(result.cameras)
    fig = Figure(figsize=(11, 3.0 + 0.12 * n), dpi=100)
    FigureCanvasAgg(fig)
    ax_off, ax_drop = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [2, 1]})
    t_sec = (g.frame_ns - result.t0_ns) / 1e9
    step = max(1, t_sec.size // max_points)
    cmap = matplotlib.colormaps["tab20"]
    for c, cam in enumerate(result.cameras):
        dev = (g.exposure_ns[::step, c] - g.frame_ns[::step]) / 1e6
        # dots, not lines: a free-running camera whose phase drifts across a group boundary jumps
        # by a whole period there
        ax_off.plot(t_sec[::step], dev, ".", ms=1.5, color=cmap(c % 20), label=cam.id if n <= 12 else None)
        dropped = cam.check.dropped_seq
        if dropped.size and cam.fit is not None:
            o = cam.check.order
            # drops sit between received frames: interpolate their time on the sequence numbers
            t_drop = np.interp(dropped, cam.seq[o], cam.exposure_ns[o])
            ax_drop.plot((t_drop - result.t0_ns) / 1e9, np.full(dropped.size, c), "|", color="tab:red", ms=8)
    for f in flashes:
        for ax in (ax_off, ax_drop):
            ax.axvspan((f.on_ns - result.t0_ns) / 1e9, (f.on_ns + f.duration_ns - result.t0_ns) / 1e9,
                       color="gold", alpha=0.3, lw=0)
    ax_off.set_ylabel("exposure - tick (ms)")
    ax_off.set_title(f"{result.sync}, {result.fps:g} FPS: exposure offsets from the group tick")
    if n <= 12:
        ax_off.legend(fontsize=7, ncol=min(n, 6), loc="upper right", markerscale=5)
    ax_drop.set_ylim(-1, n)
    ax_drop.set_yticks(range(n))
    ax_drop.set_yticklabels([c.id for c in result.cameras], fontsize=max(4, 9 - n // 10))
    ax_drop.set_ylabel("drops")
    ax_drop.set_xlabel("time since tick 0 (s)")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def refuse_overwrite(take_path: Path, force: bool) -> Path:
    """TAKE/sync_report.json; raises SyncReportExists when it is there and `force` is not set."""
    target = Path(take_path) / "sync_report.json"
    if target.exists() and not force:
        raise SyncReportExists(f"{target}: exists (use --force to recompute)")
    return target


def sync_take(path, *, force: bool = False, latency_ns: Mapping[str, float] | None = None,
              optical: bool = True, settings: SyncSettings | None = None,
              progress: Callable[[int], None] | None = None) -> dict:
    """Validate a take and write TAKE/sync_report.json, sync_report.md and sync_timeline.png.

    Refuses (SyncReportExists) to replace an existing report unless `force`; each file is written
    atomically, the JSON last, so a report on disk always has its companions."""
    from manus_core.fileio import write_atomic
    from manus_core.take import Take

    take = Take(path)
    target = refuse_overwrite(take.path, force)
    result, report = analyze_take(take, latency_ns=latency_ns, optical=optical, settings=settings,
                                  progress=progress)
    write_atomic(take.path / "sync_timeline.png", timeline_png(result, take_flashes(take)))
    write_atomic(take.path / "sync_report.md", report_markdown(report).encode())
    write_atomic(target, (json.dumps(report, indent=1) + "\n").encode())
    return report
