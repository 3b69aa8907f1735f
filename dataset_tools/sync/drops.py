"""Drops from sequence gaps, and duplicate or non-monotonic sequence numbers and timestamps."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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
    Frames lost before the first or after the last received one leave no gap: `end_drops` and
    `tick_edge_drops` find those from the take's end and the other cameras.
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


def end_drops(last_host_ns: np.ndarray, interval_ns: np.ndarray, end_ns: int) -> np.ndarray:
    """Frames each streaming camera lost after its last received one, (C,) int64.

    The recorder reads a camera until a frame arrives at or after the take's end (`end_ns`) and
    keeps that frame, so a camera whose last frame arrived earlier lost the ones after it, up to
    the one that would have arrived at the end: one per frame interval (arrival jitter is far
    below an interval). NaN (a camera without frames) counts none."""
    gap = end_ns - np.asarray(last_host_ns, np.float64)
    with np.errstate(invalid="ignore"):
        return np.where(gap > 0, np.ceil(gap / np.asarray(interval_ns, np.float64)), 0).astype(np.int64)


def tick_edge_drops(frame_index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Frames each triggered camera lost before its first and after its last received one, from
    frame groups (T,C) of one frame per trigger: every camera was triggered on every tick from the
    take's first group to its last, so the ticks outside a camera's own first..last are its
    losses (none for a camera without frames)."""
    present = np.asarray(frame_index) >= 0
    has = present.any(axis=0)
    ticks = np.flatnonzero(present.any(axis=1))
    if not ticks.size:
        return np.zeros(present.shape[1], np.int64), np.zeros(present.shape[1], np.int64)
    first = np.argmax(present, axis=0)
    last = present.shape[0] - 1 - np.argmax(present[::-1], axis=0)
    return np.where(has, first - ticks[0], 0), np.where(has, ticks[-1] - last, 0)
