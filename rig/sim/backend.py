"""The simulated cube as a camera backend: one SimulatedCube renders each take on the take's
virtual clock, lit by the simulated LED controller, and leaves its ground truth beside it."""

from __future__ import annotations

from typing import Any

from manus_core.ground_truth import FILE_NAME as TRUTH_FILE
from manus_core.rig_config import RigConfig

from ..cameras import Backend, TakeCameras, TakeSetup
from ..clock import SimTakeClock
from .cube import SimulatedCube


def take_clock(rig: RigConfig) -> SimTakeClock:
    """The take's virtual clock, at rig.toml's [sim] time_scale."""
    return SimTakeClock(time_scale=rig.sim.time_scale)


def open_take(setup: TakeSetup) -> TakeCameras:
    """The cube's cameras for one take; `finish` writes ground_truth.h5 and the session's tags.json."""
    cube = SimulatedCube(setup.rig, setup.kind, setup.duration_s, clock=setup.clock, lighting=setup.lighting)

    def finish() -> dict[str, Any]:
        out: dict[str, Any] = {"ground_truth": None}
        try:
            cube.write_ground_truth(setup.take_dir / TRUTH_FILE, setup.label_frames)
            cube.world.write_tags(setup.take_dir.parent / "tags.json")
            out["ground_truth"] = TRUTH_FILE
        except OSError as exc:
            out["ground_truth_error"] = str(exc)
        return out

    note = ("simulated cube: hardware-trigger pulse k fires at tick k" if setup.rig.sync == "hardware-trigger"
            else "simulated cube")
    return TakeCameras({c.id: cube.camera(c.id) for c in setup.cameras}, cube.t0_ns, note, finish)


BACKEND = Backend("sim", open_take, clock=take_clock)
