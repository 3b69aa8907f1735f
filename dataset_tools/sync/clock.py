"""The device clock of one camera fitted to the host clock (docs/sync.md, "The clock fit").

Times: ns on the host clock (CLOCK_MONOTONIC) unless a name says otherwise.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from manus_core.errors import SyncError


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
