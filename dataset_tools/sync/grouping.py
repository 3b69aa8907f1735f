"""Frame groups: every camera's frames assigned to the rig's nominal ticks.

This is the one grouping of the project: the sync report measures it, and annotate, segment and
the reconstruction read the groups it saved with the report (dataset_tools.sync.takes).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


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
