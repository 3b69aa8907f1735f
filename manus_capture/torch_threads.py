"""Torch on a fixed number of CPU threads, so that a piece of work gives the same bits in any process.

MKL's matrix products and torch's parallel reductions add in an order that depends on the thread
count (a surfel object trained 400 steps on 1 and on 8 threads ends up to 0.1 apart in a scale's
logarithm). A local run has one thread per core, a Dask worker one (its nanny sets
OMP_NUM_THREADS=1): the tasks of reconstruct, contacts and evaluate set the count themselves, and a
training task carries the count of the machine it was submitted from, so that a local run keeps
every core and a run on a cluster gives the same checkpoint.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

import torch

TRAIN_THREADS = len(os.sched_getaffinity(0))   # the default of --threads: the cores of the submitting machine


@contextmanager
def torch_threads(count: int) -> Iterator[None]:
    """Run the block on `count` torch threads, then go back to the count before."""
    before = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)
