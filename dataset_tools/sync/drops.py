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
