"""The sync validation on plain arrays: each camera's rows checked and its clock fitted, then all
cameras' frames grouped on the nominal ticks (SyncResult; the report is built from it)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Collection, Mapping
from dataclasses import dataclass, field

import numpy as np

from manus_core.errors import SyncError

from .clock import ClockFit, fit_clock
from .drops import SequenceCheck, check_sequence, end_drops, tick_edge_drops
from .grouping import FrameGroups, group_frames

SYNC_MODES = ("free-run", "software-trigger", "hardware-trigger")
EARLY_NS = 1e6   # an arrival this far before the earliest its timestamp allows is a timestamp fault


@dataclass(frozen=True)
class CameraSync:
    """One camera's validation. `exposure_ns` (rows,) is the host-clock mid-exposure of every row
    (NaN for rows left out); the interval statistics are over device-time intervals per sequence
    step (host arrival intervals for a camera without a device clock). `early_arrivals`: frames
    that reached the host more than EARLY_NS before the clock fit's envelope allows, which no
    transfer can do: their timestamps jumped (without a device clock: the frame rate changed)."""

    id: str
    seq: np.ndarray
    check: SequenceCheck
    fit: ClockFit | None
    exposure_ns: np.ndarray
    interval_mean_ns: float
    interval_std_ns: float
    device_clock: bool
    latency_known: bool
    early_arrivals: int = 0

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
    early = int(np.count_nonzero(h[o] < exposure[o] + fit.latency_ns - EARLY_NS))
    return CameraSync(cam, seq, check, fit, exposure, mean, std, device_clock, latency_ns is not None, early)


@dataclass(frozen=True)
class SyncSettings:
    tolerance_ms: float = 3.0        # exposures of a group should lie within this (p95)
    max_drop_pct: float = 1.0        # per camera
    optical_tolerance_ms: float = 1.0


@dataclass(frozen=True)
class SyncResult:
    """The validation of a take. `edge_drops` (C,2): frames each camera lost before its first
    and after its last received one (zeros where the take's end was not given)."""

    fps: float
    sync: str
    t0_ns: int
    cameras: tuple[CameraSync, ...]
    groups: FrameGroups
    settings: SyncSettings = field(default_factory=SyncSettings)
    edge_drops: np.ndarray | None = None


def _edge_drops(frames: Mapping[str, Mapping[str, np.ndarray]], cams: list[CameraSync], groups: FrameGroups,
                sync: str, end_ns: int, lost: Collection[str]) -> np.ndarray:
    """(C,2) frames lost before each camera's first and after its last frame, in a take that ran
    to its end: triggered in software, every camera got every tick's trigger; streaming (free-run,
    hardware trigger), every camera was read until a frame arrived at the end. Cameras lost
    during the take are left out (they stopped early)."""
    edges = np.zeros((len(cams), 2), np.int64)
    if sync == "software-trigger":
        edges[:, 0], edges[:, 1] = tick_edge_drops(groups.frame_index)
    else:
        last = [np.max(frames[c.id]["t_host_ns"]) if c.rows else np.nan for c in cams]
        interval = [c.interval_mean_ns if np.isfinite(c.interval_mean_ns) else groups.period_ns for c in cams]
        edges[:, 1] = end_drops(np.array(last, np.float64), np.array(interval), end_ns)
    edges[[c.id in lost for c in cams]] = 0
    return edges


def analyze_sync(frames: Mapping[str, Mapping[str, np.ndarray]], fps: float, *, sync: str = "free-run",
                 t0_ns: int | None = None, latency_ns: Mapping[str, float] | None = None,
                 settings: SyncSettings | None = None, end_ns: int | None = None,
                 lost: Collection[str] = ()) -> SyncResult:
    """Validate the frames of a take given as arrays: {cam: {seq, t_device_ns, t_host_ns}} (rows in
    arrival order, as in frames.csv). `latency_ns`: per camera, mid-exposure -> earliest host
    arrival, where known. `t0_ns`: the take's tick 0 (default: the first estimated exposure).
    `end_ns`: for a take that ran to its end, when the recorder ended it (take.json t0_ns +
    duration_s); frames lost at the ends of each camera's stream, which no sequence gap shows, are
    then counted too, except for the cameras in `lost` (lost during the take)."""
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
    edges = None if end_ns is None else _edge_drops(frames, cams, groups, sync, end_ns, lost)
    return SyncResult(float(fps), sync, int(t0_ns), tuple(cams), groups, settings or SyncSettings(), edges)
