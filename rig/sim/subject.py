"""A simulated rig with another object, paint or subject than its rig.toml names (record, protocol, demo)."""

from __future__ import annotations

import dataclasses

from manus_core.errors import SessionError
from manus_core.rig_config import RigConfig
from rig.sim.hand import SUBJECTS, subject_shape
from rig.sim.objects import OBJECTS


def with_sim_subject(rig: RigConfig, *, obj: str | None = None, paint: bool | None = None,
                     subject: str | None = None) -> RigConfig:
    """The rig with its simulated world's object, paint and subject replaced where given."""
    if rig.sim is None:
        return rig
    changes = {k: v for k, v in (("object", obj), ("paint", paint), ("subject", subject)) if v is not None}
    if not changes:
        return rig
    if "object" in changes and changes["object"] not in OBJECTS:
        raise SessionError(f"{rig.source}: the simulated cube has no object {changes['object']!r} "
                           f"(known: {', '.join(OBJECTS)})")
    if "subject" in changes:
        if not changes["subject"].endswith(".toml") and changes["subject"] not in SUBJECTS:
            raise SessionError(f"{rig.source}: the simulated cube has no subject {changes['subject']!r} "
                               f"(known: {', '.join(SUBJECTS)}, or a subject file NAME.toml)")
        subject_shape(changes["subject"])   # a subject file with anything impossible fails here
    return dataclasses.replace(rig, sim=dataclasses.replace(rig.sim, **changes))
