"""The record stage of `make demo`: five takes of the simulated cube, 24 cameras at 320x180, 30 fps.

Goal (issue 20): at least 4x faster than the 166 s measured with the capsule hand rendered in
numpy, which no longer exists to run beside it; the ratio is against that figure. Prints the
stage's time, frames per second, and the ratio.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from manus_capture.demo import Demo, DemoConfig

CAPSULE_HAND_S = 166.0   # the measurement of the same stage before the anatomical hand
GOAL = 4.0


def main() -> None:
    with tempfile.TemporaryDirectory() as folder:
        demo = Demo(Path(folder), DemoConfig(), say=lambda line: None)
        start = time.perf_counter()
        frames = demo.record()["frames"]
        seconds = time.perf_counter() - start
    ratio = CAPSULE_HAND_S / seconds
    print(f"{'record s':>9} {'frames':>7} {'frames/s':>9} {'x faster':>9} {'goal':>6}")
    print(f"{seconds:9.1f} {frames:7d} {frames / seconds:9.1f} {ratio:9.2f} {'met' if ratio >= GOAL else 'MISSED':>6}")


if __name__ == "__main__":
    main()
