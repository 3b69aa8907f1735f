"""What the fault battery (fault_battery.py) runs faults with: the registry, the command line, the
outcome of a fault, and the small simulated takes the faults harm."""

from __future__ import annotations

import dataclasses
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib
from collections.abc import Callable
from pathlib import Path

import tomli_w
from click.testing import CliRunner

from manus_capture.cli import cli
from manus_core.rig_config import rig_to_toml
from manus_core.take import Take
from rig.layouts import make_rig
from rig.sim.cube import true_cameras

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
BAR = re.compile(r"\d+/s\]|\d+%\|")   # a tqdm progress line


@dataclasses.dataclass(frozen=True)
class Outcome:
    handled: bool
    said: str          # the last line the user saw, or what went wrong


@dataclasses.dataclass(frozen=True)
class Fault:
    area: str
    what: str
    run: Callable[[Path], Outcome]


FAULTS: list[Fault] = []


def fault(area: str, what: str):
    def register(fn: Callable[[Path], Outcome]) -> Callable[[Path], Outcome]:
        FAULTS.append(Fault(area, what, fn))
        return fn
    return register


# --- running the command line ----------------------------------------------------------------------

def invoke(*args: object):
    return CliRunner().invoke(cli, [str(a) for a in args])


def last_line(text: str) -> str:
    """The last line a user reads, progress bars left out."""
    lines = [line for line in text.replace("\r", "\n").splitlines() if line.strip() and not BAR.search(line)]
    return (lines[-1] if lines else "(nothing)")[:160]


def said(res) -> str:
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        return f"traceback: {type(res.exception).__name__}: {res.exception}"[:160]
    return last_line(res.output)


def outcome(res, code: int, *needles: str, check: bool = True) -> Outcome:
    """Handled when the command exits with `code`, without a traceback, saying every needle, and
    `check` (the fault's own test of what is left) holds."""
    crashed = res.exception is not None and not isinstance(res.exception, SystemExit)
    ok = not crashed and res.exit_code == code and all(n in res.output for n in needles) and check
    return Outcome(ok, f"exit {res.exit_code}: {said(res)}")


def run(*args: object, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "manus_capture.cli", *map(str, args)], capture_output=True,
                          text=True, timeout=timeout, check=False)


def proc_outcome(res: subprocess.CompletedProcess, code: int, *needles: str, check: bool = True) -> Outcome:
    text = res.stdout + res.stderr
    ok = "Traceback" not in text and res.returncode == code and all(n in text for n in needles) and check
    return Outcome(ok, f"exit {res.returncode}: {last_line(text)}")


# --- fixtures ----------------------------------------------------------------------------------------

def sim_rig(seed: int = 4, **sim_values):
    rig = make_rig("cube53", cameras=6, resolution=(64, 36), fps=60.0, seed=seed)
    cams = tuple(dataclasses.replace(c, sim=dataclasses.replace(c.sim, drop_rate=0.0)) for c in rig.cameras)
    return dataclasses.replace(rig, cameras=cams, sim=dataclasses.replace(rig.sim, supersample=1, **sim_values))


def rig_doc(rig=None) -> dict:
    return tomllib.loads(rig_to_toml(rig or sim_rig()))


def write_doc(doc: dict, path: Path) -> Path:
    path.write_text(tomli_w.dumps(doc))
    return path


_TAKES: dict[str, Path] = {}


def recorded(kind: str = "grasp", duration: float = 1.0) -> Path:
    """A take recorded once per battery run on the small simulated rig (copy it before harming it)."""
    key = f"{kind}-{duration}"
    if key not in _TAKES:
        root = Path(tempfile.mkdtemp(prefix="fault-battery-"))
        rig = write_doc(rig_doc(), root / "rig.toml")
        res = invoke("record", "--rig", rig, "--session", root / "S", "--take", "t", "--kind", kind,
                     "--duration", duration, "--no-leds")
        if res.exit_code != 0:
            raise RuntimeError(f"the battery's take did not record: {res.output[-500:]}")
        true_cameras(sim_rig()).save(root / "calib" / "cameras.json")
        _TAKES[key] = root
    return _TAKES[key]


def copy_take(tmp: Path, kind: str = "grasp") -> Path:
    root = recorded(kind)
    shutil.copytree(root / "S", tmp / "S")
    shutil.copytree(root / "calib", tmp / "calib")
    return tmp / "S" / "t"


def readable(take_dir: Path) -> bool:
    """Every frames.csv row has its packet in the video, and every packet decodes."""
    import cv2

    take = Take(take_dir)
    for cam in take.cameras:
        rows = take.camera_frames(cam)["seq"]
        packets = list(take.packets(cam))
        if len(packets) < len(rows) or any(cv2.imdecode(p, cv2.IMREAD_COLOR) is None for p in packets[:len(rows)]):
            return False
    return True
