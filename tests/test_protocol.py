"""`manus-capture protocol`: every step of the capture protocol becomes a take of the right kind."""

from __future__ import annotations

import dataclasses
import json
import socket

from click.testing import CliRunner

from manus_capture.cli import cli
from manus_capture.commands.protocol import protocol_steps
from manus_core.ground_truth import GroundTruth, TruthHand, TruthObject
from manus_core.rig_config import rig_to_toml
from manus_core.session import load_session, open_session
from rig.backends import BACKENDS
from rig.layouts import make_rig
from rig.record import TakeResult


def test_protocol_steps_follow_the_paper():
    plain = protocol_steps(paint=False, repeats=3)
    assert [s.kind for s in plain] == ["calibration", "hand", "object", "grasp", "grasp", "grasp"]
    painted = protocol_steps(paint=True, repeats=2, duration_s=0.5)
    assert [s.name for s in painted] == ["00-calibration", "01-hand", "02-object", "03-grasp1",
                                         "04-canonical1", "05-grasp2", "06-canonical2"]
    assert all(s.duration_s == 0.5 for s in painted)


def test_protocol_on_the_sim_records_every_step_unattended(tmp_path):
    # 0.05 s takes are too short for the sync check to measure the clocks' drift: it is skipped
    rig = make_rig("cube53", cameras=2, resolution=(64, 36), seed=3)
    rig = dataclasses.replace(rig, sim=dataclasses.replace(rig.sim, supersample=1))
    (tmp_path / "rig.toml").write_text(rig_to_toml(rig))
    args = ["protocol", "--rig", str(tmp_path / "rig.toml"), "--session", str(tmp_path / "s"),
            "--object", "box", "--paint", "--repeats", "2", "--duration", "0.05", "--no-sync-check"]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 0, res.output
    assert "7/7 takes complete (box, painted, subject s01)" in res.output
    session = load_session(tmp_path / "s")
    steps = protocol_steps(paint=True, repeats=2)
    assert [(t["name"], t["kind"], t["status"]) for t in session.takes] == \
        [(s.name, s.kind, "complete") for s in steps]
    assert (session.object, session.paint, session.subject) == ("box", True, "s01")
    assert session.rig.sim.object == "box" and session.rig.sim.paint
    assert "sync check" not in res.output
    for step in steps:
        assert not (tmp_path / "s" / step.name / "sync_report.json").exists()
        meta = json.loads((tmp_path / "s" / step.name / "take.json").read_text())
        assert meta["kind"] == step.kind and meta["status"] == "complete" and meta["frames"] >= 2 * 6
        gt = GroundTruth.of_take(tmp_path / "s" / step.name)
        assert gt.info.kind == step.kind and gt.info.object == "box" and gt.info.paint
        assert gt.has(TruthObject) == (step.kind in ("object", "grasp"))
        assert gt.has(TruthHand) == (step.kind in ("hand", "grasp", "canonical"))
    # run again: every take is complete, nothing is recorded twice
    again = CliRunner().invoke(cli, args)
    assert again.exit_code == 0 and again.output.count("already complete, skipped") == 7


def test_protocol_rejects_an_object_the_sim_does_not_have(tmp_path):
    (tmp_path / "rig.toml").write_text(rig_to_toml(make_rig("cube53", cameras=2, resolution=(64, 36))))
    res = CliRunner().invoke(cli, ["protocol", "--rig", str(tmp_path / "rig.toml"), "--session",
                                   str(tmp_path / "s"), "--object", "banana"])
    assert res.exit_code == 2 and "no object 'banana' (known: box, mug, sphere)" in res.output


def test_protocol_prompts_the_operator_on_a_real_rig(tmp_path, monkeypatch):
    rig = make_rig("cube53", cameras=2, resolution=(64, 48), backend="aravis")
    # the lab has filled in its cameras' serials (rig check refuses rig init's CHANGE-ME placeholders)
    rig = dataclasses.replace(rig, cameras=tuple(dataclasses.replace(c, device=f"SN{k}")
                                                 for k, c in enumerate(rig.cameras)))
    (tmp_path / "rig.toml").write_text(rig_to_toml(rig))
    recorded = []

    def fake_record(rig, session, take, kind, duration_s, options, **kw):
        recorded.append((take, kind, duration_s))
        open_session(session, rig).update_take(take, kind=kind, status="complete")
        return TakeResult(session / take, "complete", "", False, [])

    monkeypatch.setattr("manus_capture.commands.protocol.record_take", fake_record)
    res = CliRunner().invoke(cli, ["protocol", "--rig", str(tmp_path / "rig.toml"), "--session",
                                   str(tmp_path / "s"), "--object", "cup", "--no-leds"], input="\ns\nq\n")
    assert recorded == [("00-calibration", "calibration", 3.0)]      # recorded, skipped, quit
    assert "01-hand (hand, 10 s): Hand articulation" in res.output
    assert res.exit_code == 1 and "1/6 takes complete (cup, subject -)" in res.output


def lab_rig(tmp_path, monkeypatch, drop_rate: float = 0.0) -> list[str]:
    """`protocol` args for a rig of "v4l2" cameras that are the simulated cube's: the protocol
    treats it as a real rig (it asks the operator), and the frames go through the whole recorder
    and sync check. 0.3 s takes: over less, the drift of the cameras' clocks is not measurable."""
    rig = make_rig("cube53", cameras=2, resolution=(64, 36), fps=30.0, seed=3)
    cams = tuple(dataclasses.replace(c, backend="v4l2", sim=dataclasses.replace(c.sim, drop_rate=drop_rate))
                 for c in rig.cameras)
    rig = dataclasses.replace(rig, cameras=cams, sim=dataclasses.replace(rig.sim, supersample=1))
    (tmp_path / "rig.toml").write_text(rig_to_toml(rig))
    cube = BACKENDS["sim"]

    def open_take(setup):
        as_sim = tuple(dataclasses.replace(c, backend="sim") for c in setup.cameras)
        return cube.open(dataclasses.replace(setup, rig=dataclasses.replace(setup.rig, cameras=as_sim),
                                             cameras=as_sim))

    monkeypatch.setitem(BACKENDS, "v4l2", dataclasses.replace(cube, name="v4l2", open=open_take))
    return ["protocol", "--rig", str(tmp_path / "rig.toml"), "--session", str(tmp_path / "s"), "--object", "cup",
            "--repeats", "2", "--duration", "0.3", "--no-leds"]


def test_protocol_yes_runs_a_session_without_a_keyboard(tmp_path, monkeypatch):
    args = lab_rig(tmp_path, monkeypatch)
    asked = CliRunner().invoke(cli, args, input="")     # no keyboard, no --yes: the first question ends it
    assert asked.exit_code == 1 and "Enter: record" in asked.output and not (tmp_path / "s" / "00-calibration").exists()
    res = CliRunner().invoke(cli, args + ["--yes"], input="")
    assert res.exit_code == 0, res.output
    assert "Enter: record" not in res.output and "5/5 takes complete (cup, subject s01)" in res.output
    assert res.output.count(": pass (") == 5
    assert [t["status"] for t in load_session(tmp_path / "s").takes] == ["complete"] * 5


def test_protocol_records_a_failing_take_again_once_unattended(tmp_path, monkeypatch):
    res = CliRunner().invoke(cli, lab_rig(tmp_path, monkeypatch, drop_rate=0.15) + ["--yes"], input="")
    assert res.exit_code == 1, res.output
    assert res.output.count("sync check fail: recording it again") == 5
    assert res.output.count("sync check fail again: kept as it is, and the session fails") == 5
    assert res.output.count("sync check: 00-calibration: fail (") == 2
    # the takes are there and whole: only their sync failed
    assert "5/5 takes complete" in res.output


def test_protocol_asks_before_recording_a_failing_take_again(tmp_path, monkeypatch):
    args = lab_rig(tmp_path, monkeypatch, drop_rate=0.15)
    res = CliRunner().invoke(cli, args, input="\ny\nn\nq\n")   # record, again: yes, again: no, quit
    assert res.exit_code == 1, res.output
    assert res.output.count("00-calibration: sync check fail: record it again?") == 2
    assert res.output.count("sync check: 00-calibration: fail (") == 2 and "01-hand (hand" in res.output
    assert not (tmp_path / "s" / "01-hand").exists()


def test_protocol_monitor_port_in_use_fails_before_the_session_starts(tmp_path):
    (tmp_path / "rig.toml").write_text(rig_to_toml(make_rig("cube53", cameras=2, resolution=(64, 36))))
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        res = CliRunner().invoke(cli, ["protocol", "--rig", str(tmp_path / "rig.toml"), "--session",
                                       str(tmp_path / "s"), "--object", "box", "--monitor", f"127.0.0.1:{port}"])
    assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1 and str(port) in res.output
    assert not (tmp_path / "s").exists()
