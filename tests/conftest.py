"""Shared fixtures: the real data beside the checkout, and small simulated rigs."""

from __future__ import annotations

import os
from pathlib import Path

# `pytest -n 2` puts one worker on each core; numerical libraries that start a thread per core on
# top of that thrash (the splatting tests ran 17x slower). Set before any test imports torch.
for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
# The commands still give torch a thread per core (`--threads`), so with both workers busy OpenMP's
# threads outnumber the cores; spinning at its barriers, each waits on threads that are not running:
# `refine` of the test demo's grasp took 44.5 s beside another 2-thread torch process, 15.0 s with
# the threads sleeping instead (12.3 s alone; alone, sleeping costs a quarter more, so only here).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data beside the checkout; tests never copy from it.

    CI always has it, so there (CI set in the environment) its absence fails the run instead of
    quietly skipping every real-data test.
    """
    if not SHARED_DATA.is_dir():
        if os.environ.get("CI"):
            pytest.fail(f"CI: real test data not found at {SHARED_DATA}")
        pytest.skip(f"real test data not found at {SHARED_DATA}")
    return SHARED_DATA
