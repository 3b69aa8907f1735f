"""The LED controller across command-line processes and takes.

One long-lived simulated controller on a real pseudo-terminal (as a lab's controller stays
plugged in all day) is driven by separate `manus-capture` processes; every check reads what the
controller's panels actually did (its timeline and flash events), not what the CLI printed.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from manus_core.rig_config import rig_to_toml
from manus_core.session import load_session
from manus_core.take import Take
from rig.layouts import make_rig
from rig.leds import SimulatedLedController, now_ns

pytestmark = pytest.mark.faults   # the fault-injection suite (docs/faults.md)

PANELS = 3


@pytest.fixture()
def sim(tmp_path):
    with SimulatedLedController(panels=PANELS, link_dir=tmp_path) as device:
        yield device


@pytest.fixture()
def rig_file(tmp_path, sim) -> Path:
    """A tiny simulated camera rig whose [leds] table points at the one controller's port."""
    rig = make_rig("cube53", cameras=2, resolution=(32, 18), seed=3)
    rig = dataclasses.replace(rig, sim=dataclasses.replace(rig.sim, supersample=1),
                              leds=dataclasses.replace(rig.leds, port=sim.path, protocol="ascii", panels=PANELS))
    path = tmp_path / "rig.toml"
    path.write_text(rig_to_toml(rig))
    return path


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "manus_capture.cli", *args], capture_output=True, text=True,
                          timeout=120, check=False)


def panels(sim: SimulatedLedController) -> list[float]:
    return sim.state_at(now_ns()).tolist()


def commands(sim: SimulatedLedController) -> list[str]:
    """The level, flash and status commands the controller executed (session handshakes left out)."""
    return [verb for _, verb in sim.executed() if verb != "HELLO"]


def test_separate_leds_processes_are_each_carried_out(sim, rig_file):
    rig = ["--rig", str(rig_file)]
    steps = [(["on"], [1.0] * PANELS, ["LVL"]),
             (["set", "0.3"], [0.3] * PANELS, ["LVL"]),
             (["set", "0.6", "--panel", "1"], [0.3, 0.6, 0.3], ["LVL"]),
             (["status"], [0.3, 0.6, 0.3], ["STAT"]),
             (["off"], [0.0] * PANELS, ["LVL"])]
    done: list[str] = []
    for args, levels, executed in steps:
        res = run_cli("leds", *args, *rig)
        assert res.returncode == 0, res.stderr
        done += executed
        assert commands(sim) == done, f"leds {' '.join(args)} was acknowledged but not carried out"
        assert panels(sim) == levels
    res = run_cli("leds", "status", *rig)
    # the state the controller has now, not a reply cached for an earlier process
    assert "levels 0.00 0.00 0.00" in res.stdout, res.stdout
    flashes = len(sim.flashes())
    assert run_cli("leds", "flash", "20", *rig).returncode == 0
    assert len(sim.flashes()) == flashes + 1
    [(start, end, level)] = sim.flashes()[flashes:]
    assert (end - start, level) == (20_000_000, 1.0)


def take_log(session: Path, take: str) -> dict:
    return json.loads((session / take / "take.json").read_text())


def test_two_takes_each_set_their_level_and_flash(tmp_path, sim, rig_file):
    session = tmp_path / "s"
    assert run_cli("leds", "on", "--rig", str(rig_file)).returncode == 0
    for take, level in [("a", 0.3), ("b", 0.7)]:
        before = len(sim.flashes())
        res = run_cli("record", "--rig", str(rig_file), "--session", str(session), "--take", take, "--kind",
                      "calibration", "--duration", "0.2", "--level", str(level), "--flash-ms", "30")
        assert res.returncode == 0, res.stdout + res.stderr
        meta = take_log(session, take)
        lvl, flash = [r for r in meta["led_log"] if r.get("cmd") in ("LVL", "FLASH")]
        assert lvl["status"] == flash["status"] == "ok"
        # the panels showed the take's level once the controller acknowledged it ...
        assert sim.state_at(lvl["t_ack_ns"]).tolist() == [level] * PANELS, f"take {take}: level never set"
        # ... and the flash really happened, between its send and its acknowledgement
        new = sim.flashes()[before:]
        assert len(new) == 1, f"take {take}: {len(new)} flashes, expected 1"
        assert flash["t_send_ns"] <= new[0][0] <= flash["t_ack_ns"]
    # each take's controller times are its own, later than the previous take's
    first, second = (take_log(session, t)["led_log"] for t in "ab")
    assert min(r["controller_t_us"] for r in second if "cmd" in r) > max(
        r["controller_t_us"] for r in first if "cmd" in r)


def test_controller_lost_mid_take_is_reported(tmp_path, sim, rig_file):
    session = tmp_path / "s"
    # three 200 ms flashes; the controller is pulled as the first one starts (its acknowledgement
    # may or may not have made it back) and stays out
    proc = subprocess.Popen([sys.executable, "-m", "manus_capture.cli", "record", "--rig", str(rig_file),
                             "--session", str(session), "--take", "t", "--kind", "calibration",
                             "--duration", "0.9", "--flash-ms", "200", "--flash-every", "0.3"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while "FLASH" not in commands(sim):
            assert time.monotonic() < deadline and proc.poll() is None, "the take never flashed"
            time.sleep(0.001)
        sim.unplug()
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 1, out + err
    lines = [line for line in out.splitlines() + err.splitlines() if sim.path in line]
    assert len(lines) == 1 and "LED" in lines[0] and "FLASH" in lines[0] and "disconnected" in lines[0], out + err
    meta = take_log(session, "t")
    commands_logged = [r for r in meta["led_log"] if "cmd" in r]
    assert not [r for r in commands_logged if r["status"] == "pending"], commands_logged
    failed = [r for r in commands_logged if r["status"] != "ok"]
    assert [(r["cmd"], r["status"]) for r in failed] == [("FLASH", "disconnected")]
    assert sim.path in failed[0]["error"]
    assert sim.path in meta["leds"]["errors"][0]
    assert meta["leds"]["status"] == "lost"
    assert load_session(session).take("t")["leds"] == "lost"
    # the frames are kept and readable
    take = Take(session / "t")
    for cam in take.cameras:
        packets = list(take.packets(cam))
        assert len(packets) == len(take.camera_frames(cam)["seq"]) > 50
        assert all(cv2.imdecode(np.frombuffer(p, np.uint8), cv2.IMREAD_COLOR) is not None for p in packets)
