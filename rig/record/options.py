"""How a take is recorded: the options of `manus-capture record`, as one record."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class RecordOptions:
    force: bool = False                 # record again over an existing take
    subject: str | None = None          # stored in session.toml (and sets the simulated subject)
    operator: str | None = None
    obj: str | None = None              # the object's name, stored in session.toml
    use_leds: bool = True               # False: leave the LED controller alone
    level: float | None = None          # LED level of the take; None: the [leds] level
    flash_ms: int | None = None         # flash the LEDs this long (optical sync check)
    flash_every_s: float = 1.0          # one flash in each window of this many seconds
    flash_level: float | None = None    # None: dark if the LEDs are at 0.5 or more, else full
    # simulated takes: the frames whose hand and object labels ground_truth.h5 renders (None: a few)
    label_frames: Sequence[int] | None = None
