"""--workers and --scheduler, shared by the commands whose work runs through dataset_tools.tasks."""

from __future__ import annotations

from collections.abc import Callable

import click

from dataset_tools.tasks import connect


def cluster_options(split: str) -> Callable[[Callable], Callable]:
    """--workers N (local processes) and --scheduler ADDR (a Dask cluster); `split` says how the
    command divides its work into tasks."""
    def decorate(fn: Callable) -> Callable:
        fn = click.option("--scheduler", default=None, metavar="ADDR", callback=_answering,
                          help="Run on a Dask cluster (tcp://HOST:PORT) instead; its workers must see the "
                               "same paths.")(fn)
        return click.option("--workers", type=click.IntRange(1), default=1, show_default=True,
                            help=f"Processes on this machine; the work is split {split}.")(fn)
    return decorate


def _answering(ctx: click.Context, param: click.Parameter, scheduler: str | None) -> str | None:
    """The scheduler is asked first, before a command reads its inputs: one that does not answer
    is named within seconds, not after minutes of preparation."""
    if scheduler is not None:
        connect(scheduler).close()
    return scheduler
