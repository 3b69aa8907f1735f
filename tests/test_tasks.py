"""dataset_tools.tasks: the local process pool's workers."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

POOL = """
import os, sys
from dataset_tools.tasks import run_tasks

if __name__ == "__main__":
    os.environ.pop("OMP_NUM_THREADS", None)
    print(" ".join(str(value) for _, value in run_tasks(os.getenv, ["OMP_NUM_THREADS"] * 4, workers=2)))
"""


def test_local_workers_share_the_cpus(tmp_path: Path) -> None:
    """Each of N local workers is given its share of the process's CPUs (OMP_NUM_THREADS, which the
    keypoint models' sessions size their threads by): every worker taking every core ran N threads
    a core, and `detect --workers 2` on 2 cores took 12.1 s against 9.9 s in one process (6.4 s
    now)."""
    script = tmp_path / "pool.py"
    script.write_text(POOL)
    out = subprocess.run([sys.executable, str(script)], cwd=Path(__file__).resolve().parents[1],
                         env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])},
                         capture_output=True, text=True, check=True).stdout.split()
    assert out == [str(max(1, len(os.sched_getaffinity(0)) // 2))] * 4
