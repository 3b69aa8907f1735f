"""The CLI's progress bars: the one place that draws them (tqdm, on stderr).

`Bars()` is a `manus_core.progress.Progress`: pass it to any library function that takes
`progress=` and it draws one bar per stage, closing a stage's bar when the next stage starts.
"""

from __future__ import annotations

import sys

from tqdm import tqdm


class _Bar(tqdm):
    # Bars sets each bar's count and redraws it itself, so tqdm's monitor thread (which tunes the
    # redraw interval of update()) has nothing to do; with it, annotate's peak memory on a 10 s take
    # was 313 or 366 MB between identical runs, without it 313 MB in each of five.
    monitor_interval = 0


class Bars:
    """One tqdm bar per stage of progress(stage, done, total); a context manager closes the last."""

    def __init__(self, unit: str = "it") -> None:
        self.unit = unit
        self.bar: _Bar | None = None
        self.stage: str | None = None

    def __call__(self, stage: str, done: int, total: int | None) -> None:
        if stage != self.stage:
            self.close()
            self.stage = stage
            self.bar = _Bar(total=total, desc=stage, unit=self.unit, file=sys.stderr)
        self.bar.n = done
        self.bar.refresh()

    def close(self) -> None:
        if self.bar is not None:
            if self.bar.total is not None:
                self.bar.n = self.bar.total  # a stage ends when the next one starts
            self.bar.close()
            self.bar = None
            self.stage = None

    def __enter__(self) -> Bars:
        return self

    def __exit__(self, kind, *exc) -> None:
        if kind is None:
            self.close()
        elif self.bar is not None:
            self.bar.close()
