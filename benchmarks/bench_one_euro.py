"""1-euro filter speed: manus-capture's one_euro against the OneEuroFilter package, side by side.

    .venv/bin/python benchmarks/bench_one_euro.py [--frames 100000] [--channels 26]

The workload of annotate: 26 joint-angle channels over 100k frames at 120 FPS with timing jitter.
The OneEuroFilter package (pip install OneEuroFilter, used only here) is the author's reference
code: one filter object per channel, one call per sample. Both run on one core and must agree.
"""

from __future__ import annotations

import os

os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from dataset_tools.one_euro import _kernel, one_euro  # noqa: E402

PARAMS = {"min_cutoff": 1.0, "beta": 0.1, "d_cutoff": 1.0}


def reference(x: np.ndarray, t: np.ndarray) -> np.ndarray:
    from OneEuroFilter import OneEuroFilter

    out = np.empty_like(x)
    for d in range(x.shape[1]):
        f = OneEuroFilter(120.0, PARAMS["min_cutoff"], PARAMS["beta"], PARAMS["d_cutoff"])
        column = x[:, d].tolist()
        times = t.tolist()
        out[:, d] = [f(v, ti) for v, ti in zip(column, times)]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100_000)
    parser.add_argument("--channels", type=int, default=26)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    # Start at t = 1 s: the reference treats a previous timestamp of 0.0 as "none".
    t = 1.0 + np.cumsum(rng.uniform(0.9, 1.1, args.frames) / 120.0)
    x = np.cumsum(rng.normal(scale=0.01, size=(args.frames, args.channels)), axis=0)
    print(f"{args.channels} channels x {args.frames} frames, 120 FPS with 10% jitter, "
          f"min_cutoff {PARAMS['min_cutoff']}, beta {PARAMS['beta']}, d_cutoff {PARAMS['d_cutoff']}; one core")

    compiled = hasattr(_kernel(), "py_func")  # a numba dispatcher wraps the Python function
    t0 = time.perf_counter()
    one_euro(x[:10], t[:10], **PARAMS)  # numba compiles (or loads its cache) on the first call
    warm = time.perf_counter() - t0
    ours = np.inf
    for _ in range(5):
        t0 = time.perf_counter()
        out = one_euro(x, t, **PARAMS)
        ours = min(ours, time.perf_counter() - t0)
    engine = "numba" if compiled else "plain Python (numba not installed)"
    print(f"manus-capture one_euro ({engine}): {ours * 1000:8.1f} ms   first call {warm:.2f} s (compile/cache)")
    try:
        import OneEuroFilter  # noqa: F401
    except ImportError:
        print("OneEuroFilter is not installed; `pip install OneEuroFilter` for the side-by-side comparison.")
        return
    t0 = time.perf_counter()
    ref = reference(x, t)
    theirs = time.perf_counter() - t0
    print(f"OneEuroFilter package (reference):   {theirs * 1000:8.1f} ms")
    print(f"max |difference| {np.abs(out - ref).max():.2e} (signal std {x.std():.2f})")
    print(f"speed-up: {theirs / ours:.0f}x (goal 50x)")


if __name__ == "__main__":
    main()
