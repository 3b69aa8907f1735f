"""numba for the toolkit's loops over pixels and points that numpy can only run as many passes
with whole-array temporaries: a function is compiled on its first call (numba's import and
compilation cost nothing to a command that never calls it) and cached on disk beside its module."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TypeVar

F = TypeVar("F", bound=Callable)


def jit(fn: F) -> F:
    """fn compiled by numba (nopython, without the GIL, cached) when it is first called."""
    compiled = None

    @functools.wraps(fn)
    def call(*args):
        nonlocal compiled
        if compiled is None:
            import numba

            compiled = numba.njit(cache=True, nogil=True)(fn)
        return compiled(*args)

    return call  # type: ignore[return-value]
