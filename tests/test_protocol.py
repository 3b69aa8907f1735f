"""`manus-capture protocol`: every step of the capture protocol becomes a take of the right kind."""

from __future__ import annotations

import dataclasses
import json

from click.testing import CliRunner

from manus_capture.cli import cli
from manus_capture.commands.protocol import protocol_steps
from manus_core.ground_truth import GroundTruth, TruthHand, TruthObject
from manus_core.rig_config import rig_to_toml
from manus_core.session import load_session, open_session
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
    rig = make_rig("cube53", cameras=2, resolution=(64, 36), seed=3)
    rig = dataclasses.replace(rig, sim=dataclasses.replace(rig.sim, supersample=1))
    (tmp_path / "rig.toml").write_text(rig_to_toml(rig))
    args = ["protocol", "--rig", str(tmp_path / "rig.toml"), "--session", str(tmp_path / "s"),
            "--object", "box", "--paint", "--repeats", "2", "--duration", "0.05"]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 0, res.output
    assert "7/7 takes complete (box, painted, subject s01)" in res.output
    session = load_session(tmp_path / "s")
    steps = protocol_steps(paint=True, repeats=2)
    assert [(t["name"], t["kind"], t["status"]) for t in session.takes] == \
        [(s.name, s.kind, "complete") for s in steps]
    assert (session.object, session.paint, session.subject) == ("box", True, "s01")
    assert session.rig.sim.object == "box" and session.rig.sim.paint
    for step in steps:
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
