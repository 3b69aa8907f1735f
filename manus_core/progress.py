"""One way for library code to report progress; only the CLI draws bars.

A long-running function takes `progress: Progress = silent` and calls
`progress(stage, done, total)` as work advances: `stage` names the step ("detect", "render"),
`done` counts finished units and `total` is how many there will be (None when unknown). It never
prints. The CLI passes `manus_capture.bars.Bars()`, which draws one bar per stage.
"""

from __future__ import annotations

from typing import Protocol


class Progress(Protocol):
    def __call__(self, stage: str, done: int, total: int | None) -> None: ...


def silent(stage: str, done: int, total: int | None) -> None:
    """The default: report nothing."""
