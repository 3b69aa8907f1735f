"""The 1-euro filter (Casiez, Roussel and Vogel, CHI 2012) over many channels at once.

    smoothed = one_euro(x, t, min_cutoff=1.0, beta=0.0, d_cutoff=1.0)

Each channel is an adaptive exponential low-pass filter whose cutoff rises with the speed of the
signal: cutoff = min_cutoff + beta * |filtered derivative|. The arithmetic follows the author's
reference implementation (casiez/OneEuroFilter): alpha = 1 / (1 + tau / te) with
tau = 1 / (2 pi cutoff) and te the time since the previous sample; the derivative is taken against
the previous *filtered* value and low-passed with d_cutoff; the first sample passes through and
its derivative is 0.

Beyond the reference:
- te comes from the timestamps of every step, so uneven frame intervals are handled. (The
  reference re-estimates its frequency the same way but ignores a previous timestamp of exactly
  0.0 and uses its configured frequency then; from a real clock the two are the same filter.)
- NaN marks a missing sample: the output is NaN there (nothing is invented), the channel's state is
  held, and its next sample is filtered over the whole gap (te = time since the last sample seen),
  so a long gap lets the output catch up with the input instead of crawling towards it.

The recursion in time is sequential by nature. It runs in one compiled loop over time and channels
(numba, when it is installed: some 400x faster than the reference on 26 channels); without numba
the very same loop runs as plain Python, with the same results but about as slow as the reference.
"""

from __future__ import annotations

import math

import numpy as np

from manus_core.errors import OneEuroError


def _one_euro_loop(x: np.ndarray, t: np.ndarray, min_cutoff: float, beta: float,
                   d_cutoff: float) -> np.ndarray:
    """x (T,D) float64 with NaN for missing samples, t (T,) strictly increasing seconds."""
    n_t, n_d = x.shape
    out = np.empty((n_t, n_d))
    x_hat = np.zeros(n_d)
    dx_hat = np.zeros(n_d)
    # -inf makes te infinite on a channel's first sample, which gives alpha = 1 (output = input)
    # and a zero derivative without a branch of its own.
    t_last = np.full(n_d, -np.inf)
    t_prev = -np.inf
    two_pi = 2.0 * math.pi
    for i in range(n_t):
        ti = t[i]
        # Most channels were last seen on the previous row: compute that row's constants once.
        te_row = ti - t_prev
        r_row = two_pi * d_cutoff * te_row
        a_d_row = r_row / (1.0 + r_row) if math.isfinite(r_row) else 1.0
        for d in range(n_d):
            xi = x[i, d]
            if not math.isfinite(xi):
                out[i, d] = math.nan
                continue
            if t_last[d] == t_prev:
                te = te_row
                a_d = a_d_row
            else:
                te = ti - t_last[d]
                r_d = two_pi * d_cutoff * te
                a_d = r_d / (1.0 + r_d) if math.isfinite(r_d) else 1.0
            step = xi - x_hat[d]
            dxh = dx_hat[d] + a_d * (step / te - dx_hat[d])
            r = two_pi * te * (min_cutoff + beta * abs(dxh))
            a = r / (1.0 + r) if math.isfinite(r) else 1.0
            xh = x_hat[d] + a * step
            x_hat[d] = xh
            dx_hat[d] = dxh
            t_last[d] = ti
            out[i, d] = xh
        t_prev = ti
    return out


_compiled = None


def _kernel():
    """The loop compiled with numba (cached on disk), or the plain-Python loop without numba."""
    global _compiled
    if _compiled is None:
        try:
            import numba
        except ImportError:
            _compiled = _one_euro_loop
        else:
            _compiled = numba.njit(cache=True, nogil=True)(_one_euro_loop)
    return _compiled


def one_euro(x: np.ndarray, t: np.ndarray, min_cutoff: float = 1.0, beta: float = 0.0,
             d_cutoff: float = 1.0) -> np.ndarray:
    """Filter x (T, ...) sampled at times t (T,) in seconds; returns an array shaped like x.

    Every trailing dimension is an independent channel (joint angles (T,26), joints (T,21,3)).
    min_cutoff and d_cutoff are in Hz (> 0); beta (>= 0) is in 1/(unit of x): raise it to cut lag
    on fast motion, lower min_cutoff to cut jitter at rest. NaN (or inf) in x is a missing sample
    and is NaN in the output. t must be finite and strictly increasing.
    """
    x = np.asarray(x, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if x.ndim == 0:
        raise OneEuroError("one_euro: x must have a time axis, got a scalar")
    if t.shape != (x.shape[0],):
        raise OneEuroError(f"one_euro: t has shape {t.shape}, expected ({x.shape[0]},) to match x {x.shape}")
    if not np.isfinite(t).all():
        raise OneEuroError(f"one_euro: t has {int((~np.isfinite(t)).sum())} non-finite timestamps")
    steps = np.diff(t)
    if (steps <= 0).any():
        i = int(np.argmax(steps <= 0))
        raise OneEuroError(f"one_euro: timestamps must increase strictly; t[{i + 1}] = {float(t[i + 1])!r} "
                           f"follows t[{i}] = {float(t[i])!r}")
    for name, value, low_ok in (("min_cutoff", min_cutoff, False), ("d_cutoff", d_cutoff, False),
                                ("beta", beta, True)):
        if not (math.isfinite(value) and (value >= 0 if low_ok else value > 0)):
            raise OneEuroError(f"one_euro: {name} = {value!r} must be {'>= 0' if low_ok else '> 0'} and finite")
    flat = np.ascontiguousarray(x.reshape(x.shape[0], -1))
    out = _kernel()(flat, np.ascontiguousarray(t), float(min_cutoff), float(beta), float(d_cutoff))
    return out.reshape(x.shape)
