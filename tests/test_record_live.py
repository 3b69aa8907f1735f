"""The recorder as a monitor sees it (rig.record.live), `record --monitor`, and the sync verdict
`record` gives after every take."""

from __future__ import annotations

import dataclasses
import json
import re
import socket
import threading
import time
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from manus_capture.cli import cli
from manus_capture.monitor import start_monitor
from manus_core.rig_config import rig_to_toml
from rig.layouts import make_rig
from rig.record import LiveSession, RecordOptions, record_take


def tiny_rig(cameras: int = 3, drop_rate: float = 0.0, time_scale: float = 0.0):
    """A simulated rig of 64x36 cameras; time_scale 1 records in real time (0: as fast as it renders)."""
    rig = make_rig("cube53", cameras=cameras, resolution=(64, 36), seed=3)
    cams = tuple(dataclasses.replace(c, sim=dataclasses.replace(c.sim, drop_rate=drop_rate)) for c in rig.cameras)
    sim = dataclasses.replace(rig.sim, supersample=1, time_scale=time_scale)
    return dataclasses.replace(rig, cameras=cams, sim=sim)


def record_args(tmp_path: Path, rig, take: str = "t", duration: str = "0.3") -> list[str]:
    rig_file = tmp_path / "rig.toml"
    rig_file.write_text(rig_to_toml(rig))
    return ["record", "--rig", str(rig_file), "--session", str(tmp_path / "s"), "--take", take,
            "--kind", "calibration", "--duration", duration, "--no-leds"]


def in_thread(fn) -> tuple[threading.Thread, dict]:
    out: dict = {}

    def run() -> None:
        try:
            out["result"] = fn()
        except BaseException as exc:
            out["error"] = exc

    thread = threading.Thread(target=run)
    thread.start()
    return thread, out


def wait_for(predicate, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.02)


def test_live_counters_rise_during_a_take_and_the_latest_jpeg_decodes(tmp_path):
    rig = tiny_rig(time_scale=1.0)
    source = LiveSession(rig, tmp_path / "s", total=1)
    ids = [c.id for c in rig.cameras]
    waiting = source.snapshot()
    assert waiting["status"] == "waiting" and [c["id"] for c in waiting["cameras"]] == ids
    assert source.latest_jpeg(ids[0]) is None and waiting["disk"]["free_bytes"] > 0
    with pytest.raises(KeyError):
        source.latest_jpeg("nope")
    thread, out = in_thread(lambda: record_take(rig, tmp_path / "s", "t", "calibration", 1.0,
                                                RecordOptions(flash_ms=50), on_live=source.attach))
    snaps = []
    try:
        wait_for(lambda: source.live is not None)
        while thread.is_alive():
            snaps.append(source.snapshot())
            time.sleep(0.1)
        during = [s for s in snaps if s["status"] == "recording" and 0 < s["elapsed_s"]]
        mid = next(s for s in during if all(c["frames"] > 0 for c in s["cameras"]))
        image = cv2.imdecode(np.frombuffer(source.latest_jpeg(ids[1]), np.uint8), cv2.IMREAD_COLOR)
    finally:
        thread.join()
    assert "error" not in out, out
    result = out["result"]
    final = source.snapshot()
    assert final["status"] == "complete" and final["take"] == "t" and final["session"] == "s"
    assert image.shape == (36, 64, 3)
    frames = {c.id: c.frames for c in result.cameras}
    assert {c["id"]: c["frames"] for c in final["cameras"]} == frames
    assert all(0 < c["frames"] < frames[c["id"]] for c in mid["cameras"])   # counted while recording
    assert [s["elapsed_s"] for s in during] == sorted(s["elapsed_s"] for s in during)
    assert len(during) >= 4 and final["elapsed_s"] == pytest.approx(1.0)
    assert all(0 <= c["buffer_fill"] <= 1 and c["status"] == "ok" for s in snaps for c in s["cameras"])
    assert final["disk"]["written_bytes"] == sum(c.bytes for c in result.cameras) > 0
    assert final["disk"]["free_bytes"] > 0 and final["disk"]["min_free_gb"] == rig.storage.min_free_gb
    assert final["leds"]["status"] == "ok" and final["leds"]["flashes"] == 1
    assert final["cameras"][0]["last_frame_ns"] <= final["t_ns"]
    assert final["session_progress"] == {"done": 0, "total": 1, "last_take": None, "last_verdict": None}
    with pytest.raises(KeyError):
        source.latest_jpeg("nope")
    # the API records; the verdict is the commands' business
    assert not (tmp_path / "s" / "t" / "sync_report.json").exists()


def test_record_prints_the_verdict_and_no_sync_check_skips_it(tmp_path):
    args = record_args(tmp_path, tiny_rig(cameras=2))
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 0, res.output
    assert "sync check: t: pass (" in res.output
    take = tmp_path / "s" / "t"
    report = json.loads((take / "sync_report.json").read_text())
    assert report["verdict"] == "pass" and (take / "sync_report.md").exists()
    skipped = CliRunner().invoke(cli, record_args(tmp_path, tiny_rig(cameras=2), take="u") + ["--no-sync-check"])
    assert skipped.exit_code == 0, skipped.output
    assert "sync check" not in skipped.output and not (tmp_path / "s" / "u" / "sync_report.json").exists()


def test_record_exits_1_when_the_verdict_fails(tmp_path):
    res = CliRunner().invoke(cli, record_args(tmp_path, tiny_rig(cameras=2, drop_rate=0.1)))
    assert res.exit_code == 1, res.output
    assert "take " in res.output and ": complete, 2 cameras" in res.output   # the take itself is whole
    assert "sync check: t: fail (" in res.output and "fail: " in res.output and "drop" in res.output
    assert json.loads((tmp_path / "s" / "t" / "sync_report.json").read_text())["verdict"] == "fail"


def test_monitor_port_in_use_fails_before_any_camera_opens(tmp_path):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        res = CliRunner().invoke(cli, record_args(tmp_path, tiny_rig(cameras=2)) + ["--monitor", str(port)])
    assert res.exit_code == 2, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and str(port) in lines[0], res.output
    assert not (tmp_path / "s").exists()


def test_record_serves_the_monitor_and_prints_its_url(tmp_path):
    res = CliRunner().invoke(cli, record_args(tmp_path, tiny_rig(cameras=2)) + ["--monitor", "0"])
    assert res.exit_code == 0, res.output
    url = re.search(r"monitor: (http://127\.0\.0\.1:\d+/)\n", res.output)
    assert url and "sync check: t: pass" in res.output, res.output
    with pytest.raises(OSError):   # stopped with the command
        urllib.request.urlopen(url[1] + "api/status", timeout=2)


class Breaking:
    """A monitor's view of a live take that starts failing once asked to (a bug on the monitor's
    side); the recording goes on with the real object."""

    def __init__(self, inner: LiveSession) -> None:
        self.inner, self.broken = inner, False

    def _check(self) -> None:
        if self.broken:
            raise RuntimeError("the monitor's view broke")

    def camera_ids(self) -> list[str]:
        self._check()
        return self.inner.camera_ids()

    def snapshot(self) -> dict:
        self._check()
        return self.inner.snapshot()

    def latest_jpeg(self, cam: str) -> bytes | None:
        self._check()
        return self.inner.latest_jpeg(cam)


@pytest.mark.parametrize("end", ["stopped", "failing"])
def test_monitor_ended_mid_take_leaves_the_take_complete(tmp_path, end):
    rig = tiny_rig(time_scale=1.0)
    source = LiveSession(rig, tmp_path / "s")
    view = Breaking(source)
    server = start_monitor(view, "127.0.0.1", 0, None)
    thread, out = in_thread(lambda: record_take(rig, tmp_path / "s", "t", "calibration", 1.0,
                                                RecordOptions(use_leds=False), on_live=source.attach))
    status = server.url.rstrip("/") + "/api/status"
    try:
        def serving() -> bool:
            with urllib.request.urlopen(status, timeout=5) as r:
                return sum(c["frames"] for c in json.load(r)["cameras"]) > 0

        wait_for(serving)
        if end == "failing":
            view.broken = True

            def reports_it() -> bool:
                with urllib.request.urlopen(status, timeout=5) as r:
                    return "broke" in (json.load(r)["source_error"] or "")

            wait_for(reports_it)
            assert thread.is_alive() and server.running   # the page says so; neither stops
    finally:
        server.stop()
    assert thread.is_alive()   # ended mid-take
    thread.join()
    assert "error" not in out, out
    result = out["result"]
    meta = json.loads((tmp_path / "s" / "t" / "take.json").read_text())
    assert result.status == meta["status"] == "complete" and result.exit_code == 0
    assert meta["frames"] == result.frames >= 3 * 100
