"""The 1-euro filter against the author's ground truth, and its handling of gaps and uneven time."""

from __future__ import annotations

import numpy as np
import pytest

from dataset_tools.one_euro import _one_euro_loop, one_euro
from manus_core.errors import OneEuroError


def test_matches_the_authors_ground_truth(shared_data):
    """groundTruth.csv: 120 Hz, mincutoff 1.0, beta 0.1, dcutoff 1.0; upstream's test allows 1e-4."""
    data = np.loadtxt(shared_data / "oneeurofilter_casiez" / "groundTruth.csv", delimiter=",", skiprows=1)
    assert data.shape == (1200, 4)
    t, noisy, filtered = data[:, 0], data[:, 2], data[:, 3]
    out = one_euro(noisy, t, min_cutoff=1.0, beta=0.1, d_cutoff=1.0)
    assert out[0] == noisy[0]
    assert np.abs(out - filtered).max() < 1e-4
    # Many channels at once give each channel's own result.
    stacked = np.stack([noisy, -2 * noisy, noisy + 5], axis=1)
    out3 = one_euro(stacked, t, 1.0, 0.1, 1.0)
    np.testing.assert_allclose(out3[:, 0], out, rtol=0, atol=0)
    assert np.abs(out3[:, 2] - (filtered + 5)).max() < 1e-4


def test_missing_samples_stay_missing_and_are_skipped():
    """A NaN sample leaves the state alone: the channel equals the filter run without that sample."""
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.005, 0.02, 400))
    x = np.cumsum(rng.normal(size=(400, 3)), axis=0)
    x_missing = x.copy()
    gaps = [np.array([0, 1, 50, 51, 52, 300]), np.array([399]), np.arange(100, 180)]
    for d, rows in enumerate(gaps):
        x_missing[rows, d] = np.nan
    out = one_euro(x_missing, t, min_cutoff=0.7, beta=0.05)
    for d, rows in enumerate(gaps):
        keep = np.setdiff1d(np.arange(400), rows)
        assert np.isnan(out[rows, d]).all()
        expected = one_euro(x[keep, d], t[keep], min_cutoff=0.7, beta=0.05)
        np.testing.assert_allclose(out[keep, d], expected, rtol=0, atol=1e-12)
    assert np.isnan(one_euro(np.full((5, 2), np.nan), np.arange(5.0))).all()


def test_uneven_timestamps_give_the_continuous_time_lag():
    """On a ramp x = v t with beta = 0, alpha = 1 / (1 + tau / te) makes the lag settle at exactly
    v * tau, tau = 1 / (2 pi min_cutoff), whatever the frame intervals: the check that te is taken
    from every step (a fixed rate would make the lag follow the jitter)."""
    rng = np.random.default_rng(1)
    t = np.cumsum(rng.uniform(0.002, 0.05, 3000))
    v = 3.0
    out = one_euro(v * t, t, min_cutoff=2.0, beta=0.0)
    lag = v * t - out
    np.testing.assert_allclose(lag[-500:], v / (2 * np.pi * 2.0), rtol=1e-9)


def test_shapes_are_kept_and_the_python_loop_agrees():
    rng = np.random.default_rng(2)
    t = np.arange(200) / 120.0
    x = rng.normal(size=(200, 21, 3))
    out = one_euro(x, t, 1.5, 0.2, 1.0)
    assert out.shape == x.shape
    # The compiled loop and the plain-Python one (used without numba) are the same code.
    plain = _one_euro_loop(x.reshape(200, -1), t, 1.5, 0.2, 1.0)
    np.testing.assert_allclose(out.reshape(200, -1), plain, rtol=0, atol=1e-12)


def test_bad_input():
    assert OneEuroError.exit_code == 2
    with pytest.raises(OneEuroError, match=r"t has shape \(3,\), expected \(4,\)"):
        one_euro(np.zeros((4, 2)), np.arange(3.0))
    with pytest.raises(OneEuroError, match=r"increase strictly; t\[2\] = 1.0 follows t\[1\] = 1.0"):
        one_euro(np.zeros(3), np.array([0.0, 1.0, 1.0]))
    with pytest.raises(OneEuroError, match="non-finite"):
        one_euro(np.zeros(3), np.array([0.0, np.nan, 1.0]))
    with pytest.raises(OneEuroError, match="min_cutoff"):
        one_euro(np.zeros(3), np.arange(3.0), min_cutoff=0.0)
    with pytest.raises(OneEuroError, match="beta"):
        one_euro(np.zeros(3), np.arange(3.0), beta=-1.0)
