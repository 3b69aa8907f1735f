"""The recorder against the simulated cube's ground truth: every frame a camera delivered is in the
take, readable, in frames.csv and in its video; faults and signals finish every file."""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import json
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from manus_capture.cli import cli
from manus_core.errors import CameraDisconnected
from manus_core.ground_truth import GroundTruth
from manus_core.rig_config import rig_to_toml
from manus_core.session import load_session
from manus_core.take import Take
from rig.backends import BACKENDS
from rig.layouts import make_rig
from rig.mkv import MkvWriter
from rig.record import RecordOptions, StopFlag, flash_offsets, record_take

PERIOD_NS = 1e9 / 120


def sim_rig(cameras=3, sync="free-run", drop_rate=0.0, **storage):
    rig = make_rig("cube53", cameras=cameras, resolution=(96, 54), sync=sync, seed=5)
    cams = tuple(dataclasses.replace(c, sim=dataclasses.replace(c.sim, drop_rate=drop_rate)) for c in rig.cameras)
    return dataclasses.replace(rig, cameras=cams, storage=dataclasses.replace(rig.storage, **storage))


def wrap_backend(monkeypatch, name: str, wrap) -> None:
    """Register, in place of backend `name`, one whose cameras are wrap(id, camera) (a test's fake)."""
    inner = BACKENDS[name]

    def open_take(setup):
        opened = inner.open(setup)
        return dataclasses.replace(opened, cameras={k: wrap(k, v) for k, v in opened.cameras.items()})

    monkeypatch.setitem(BACKENDS, name, dataclasses.replace(inner, open=open_take))


def write_rig(rig, path: Path) -> Path:
    path.write_text(rig_to_toml(rig))
    return path


def truth(take_dir: Path):
    gt = GroundTruth.of_take(take_dir)
    return list(gt.cameras.ids), gt.frames.exposure_mid_ns, gt.frames.dropped


def check_readable(take_dir: Path, killed: bool = False) -> dict[str, int]:
    """Every camera: frames.csv rows == packets == decodable JPEGs, bytes as in frames.csv. A
    killed recorder may have written one batch's packets and not yet their rows: then packets may
    outnumber rows, and every row still has its packet."""
    take = Take(take_dir)
    counts = {}
    for cam in take.cameras:
        rows = take.camera_frames(cam)
        packets = list(take.packets(cam))
        assert len(packets) >= len(rows["seq"]) if killed else len(packets) == len(rows["seq"]), cam
        packets = packets[:len(rows["seq"])]
        assert [p.size for p in packets] == rows["bytes"].tolist(), cam
        assert all(cv2.imdecode(p, cv2.IMREAD_COLOR) is not None for p in packets), cam
        counts[cam] = len(packets)
    return counts


def test_sim_take_stores_every_delivered_frame_and_the_flashes(tmp_path):
    rig = sim_rig(drop_rate=0.06)
    result = record_take(rig, tmp_path / "s", "t1", "calibration", 0.3, RecordOptions(flash_ms=40, flash_every_s=0.15))
    take_dir = tmp_path / "s" / "t1"
    meta = json.loads((take_dir / "take.json").read_text())
    assert result.status == meta["status"] == "complete" and result.exit_code == 0
    assert meta["kind"] == "calibration" and meta["sync"] == "free-run" and meta["resolution"] == [96, 54]
    counts = check_readable(take_dir)
    ids, exposure, dropped = truth(take_dir)
    take = Take(take_dir)
    end = meta["t0_ns"] + 0.3e9
    n_drops = 0
    for c, cam in enumerate(ids):
        rows = take.camera_frames(cam)
        delivered = np.flatnonzero((exposure[c] >= 0) & ~dropped[c])
        assert counts[cam] == len(delivered)                     # every delivered frame, nothing else
        assert rows["seq"].tolist() == delivered.tolist()        # free-run: seq k is tick k
        gaps = sorted(set(range(rows["seq"][0], rows["seq"][-1] + 1)) - set(rows["seq"].tolist()))
        assert gaps == np.flatnonzero(dropped[c]).tolist()       # every gap is an injected drop
        report = next(r for r in meta["cameras"] if r["id"] == cam)
        assert report["seq_gaps"] == len(gaps) and report["frames"] == counts[cam]
        n_drops += len(gaps)
        # rows sit on the right ticks: arrival = mid-exposure + 1 ms + 1.5..3 ms transfer + tail
        latency_ms = (rows["t_host_ns"] - exposure[c, rows["seq"]]) / 1e6
        assert latency_ms.min() > 2.4 and latency_ms.max() < 8.0
        # the take ends with the first frame that arrives after the duration
        assert rows["t_host_ns"][-1] >= end and rows["t_host_ns"][-2] < end
    assert n_drops >= 3
    # the LED flashes are in exactly the frames exposed during them (the sim's lighting follows
    # the simulated controller, mapped onto the take's clock)
    flashes = meta["flashes"]
    assert [f["ms"] for f in flashes] == [40, 40] and all(f["level"] == 0.0 for f in flashes)
    assert meta["led_log"][0]["cmd"] == "LVL" and [r["cmd"] for r in meta["led_log"][1:]] == ["FLASH", "FLASH"]
    for c, cam in enumerate(ids):
        seq = take.camera_frames(cam)["seq"]
        brightness = np.array([img.mean() for _, img in take.iter_frames(cam)])
        dark = brightness < (brightness.max() + brightness.min()) / 2
        t = exposure[c, seq]
        surely_dark = np.zeros(len(t), bool)
        surely_bright = np.ones(len(t), bool)
        for f in flashes:
            surely_dark |= (t >= f["t_ack_clock_ns"]) & (t < f["t_clock_ns"] + 40e6)
            surely_bright &= (t < f["t_clock_ns"]) | (t >= f["t_ack_clock_ns"] + 40e6)
        assert np.all(dark[surely_dark]) and not np.any(dark[surely_bright])
        assert surely_dark.sum() >= 5
    session = load_session(tmp_path / "s")
    assert session.take("t1")["status"] == "complete" and session.take("t1")["frames"] == sum(counts.values())
    assert json.loads((tmp_path / "s" / "tags.json").read_text())["family"] == "tag36h11"


def test_software_trigger_one_frame_per_camera_per_tick(tmp_path):
    rig = sim_rig(sync="software-trigger")
    record_take(rig, tmp_path / "s", "t", "calibration", 0.2, RecordOptions(use_leds=False))
    take_dir = tmp_path / "s" / "t"
    meta = json.loads((take_dir / "take.json").read_text())
    ticks = meta["triggers"]
    assert ticks["source"] == "software" and ticks["tick"] == list(range(24))   # 0.2 s at 120 FPS
    nominal = meta["t0_ns"] + np.round(np.arange(24) * PERIOD_NS)
    assert np.array_equal(ticks["t_sent_ns"], nominal)
    counts = check_readable(take_dir)
    ids, exposure, dropped = truth(take_dir)
    take = Take(take_dir)
    latency = {c.id: c.sim.trigger_latency_us * 1e3 for c in rig.cameras}
    for c, cam in enumerate(ids):
        assert exposure.shape[1] == 24 and np.all(exposure[c] > 0) and not dropped[c].any()
        assert counts[cam] == 24 and take.camera_frames(cam)["seq"].tolist() == list(range(24))
        # each exposure follows its own tick's trigger by the camera's latency (30 us jitter)
        assert np.abs(exposure[c] - nominal - latency[cam]).max() < 150_000


def test_hardware_trigger_logs_the_controller_pulses(tmp_path):
    rig = sim_rig(sync="hardware-trigger")
    record_take(rig, tmp_path / "s", "t", "calibration", 0.1)
    meta = json.loads((tmp_path / "s" / "t" / "take.json").read_text())
    trig = meta["triggers"]
    assert trig["source"] == "controller"
    assert trig["controller"]["p0"] == 0 and trig["controller"]["rate_hz"] == 120.0
    assert trig["controller"]["pulses"] >= 1
    cmds = [(r["cmd"], r["args"]) for r in meta["led_log"]]
    assert ("TRIG", [120000, 0, 100]) in cmds and ("TRIG", [0, 0, 0]) in cmds
    assert check_readable(tmp_path / "s" / "t")


class Disconnecting:
    """A camera that goes away after `after` frames."""

    def __init__(self, inner, after: int) -> None:
        self.inner, self.after, self.n = inner, after, 0

    def read(self, timeout_s: float = 1.0):
        if self.n >= self.after:
            raise CameraDisconnected("camera unplugged")
        self.n += 1
        return self.inner.read(timeout_s)

    def __getattr__(self, name):
        return getattr(self.inner, name)


@pytest.mark.faults
def test_lost_camera_is_reported_and_the_others_go_on(tmp_path, monkeypatch):
    rig = sim_rig()
    lost = rig.cameras[1].id
    wrap_backend(monkeypatch, "sim", lambda cid, cam: Disconnecting(cam, 10) if cid == lost else cam)
    result = record_take(rig, tmp_path / "s", "t", "calibration", 0.25, RecordOptions(use_leds=False))
    take_dir = tmp_path / "s" / "t"
    meta = json.loads((take_dir / "take.json").read_text())
    assert meta["status"] == "complete" and meta["lost_cameras"] == [lost] and result.exit_code == 1
    report = next(r for r in meta["cameras"] if r["id"] == lost)
    assert report["status"] == "disconnected" and "unplugged" in report["error"]
    counts = check_readable(take_dir)
    ids, exposure, dropped = truth(take_dir)
    for c, cam in enumerate(ids):
        delivered = int(((exposure[c] >= 0) & ~dropped[c]).sum())
        assert counts[cam] == (10 if cam == lost else delivered)
        if cam != lost:
            assert delivered >= 30
    assert load_session(tmp_path / "s").take("t")["lost_cameras"] == [lost]


@pytest.mark.faults
def test_failing_writer_interrupts_the_take_and_keeps_every_file_readable(tmp_path, monkeypatch):
    rig = sim_rig()
    victim = rig.cameras[0].id
    real_write = MkvWriter.write

    def write(self, jpegs):
        if self.path.stem == victim and self.frames + len(jpegs) > 12:
            raise OSError(errno.EIO, "Input/output error")
        real_write(self, jpegs)

    monkeypatch.setattr(MkvWriter, "write", write)
    result = record_take(rig, tmp_path / "s", "t", "calibration", 2.0, RecordOptions(use_leds=False))
    meta = json.loads((tmp_path / "s" / "t" / "take.json").read_text())
    assert result.status == meta["status"] == "interrupted" and result.exit_code == 1
    assert meta["reason"].startswith(f"writer of camera {victim} failed: OSError")
    counts = check_readable(tmp_path / "s" / "t")
    assert counts[victim] == 12 and all(n < 240 for n in counts.values())
    assert load_session(tmp_path / "s").take("t")["status"] == "interrupted"


@pytest.mark.faults
def test_full_disk_finishes_the_take(tmp_path):
    """A real ENOSPC: the session lives on a small tmpfs that fills up during the take."""
    if shutil.which("unshare") is None or subprocess.run(
            ["unshare", "-rm", "true"], capture_output=True).returncode != 0:
        pytest.skip("unprivileged mount namespaces (unshare -rm) are not available")
    rig_file = write_rig(sim_rig(min_free_gb=0.0), tmp_path / "rig.toml")
    disk, out = tmp_path / "disk", tmp_path / "out"
    disk.mkdir()
    script = f"""
        mount -t tmpfs -o size=48m tmpfs {disk} || exit 90
        {sys.executable} -m manus_capture.cli record --rig {rig_file} --session {disk}/s --take t \\
            --kind calibration --duration 5 > {tmp_path}/stdout 2> {tmp_path}/stderr &
        pid=$!
        while [ "$(wc -l < {disk}/s/t/frames.csv 2>/dev/null || echo 0)" -lt 40 ]; do sleep 0.05; done
        dd if=/dev/zero of={disk}/fill bs=1M 2> /dev/null
        wait $pid; echo $? > {tmp_path}/rc
        rm {disk}/fill; cp -a {disk}/s {out}
    """
    done = subprocess.run(["unshare", "-rm", "sh", "-c", script], timeout=120)
    if done.returncode == 90:
        pytest.skip("cannot mount a tmpfs in a mount namespace here")
    assert int((tmp_path / "rc").read_text()) == 1, (tmp_path / "stderr").read_text()[-2000:]
    meta = json.loads((out / "t" / "take.json").read_text())
    assert meta["status"] == "interrupted" and meta["reason"].startswith("disk full (ENOSPC)")
    counts = check_readable(out / "t")
    assert sum(counts.values()) >= 40 and all(n < 600 for n in counts.values())
    assert "disk full" in (tmp_path / "stdout").read_text()


@contextlib.contextmanager
def recording(rig, tmp_path: Path, rows: int = 60) -> Iterator[subprocess.Popen]:
    """`record` of a 60 s take TMP/s/t in a process of its own, once frames.csv has `rows` rows."""
    rig_file = write_rig(rig, tmp_path / "rig.toml")
    proc = subprocess.Popen([sys.executable, "-m", "manus_capture.cli", "record", "--rig", str(rig_file),
                             "--session", str(tmp_path / "s"), "--take", "t", "--kind", "calibration",
                             "--duration", "60"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        csv = tmp_path / "s" / "t" / "frames.csv"
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not (csv.exists() and csv.read_text().count("\n") > rows):
            time.sleep(0.05)
        yield proc
    finally:
        proc.kill()


@pytest.mark.faults
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_signal_stops_the_take_in_order(tmp_path, signum):
    take_dir = tmp_path / "s" / "t"
    with recording(sim_rig(drop_rate=0.02), tmp_path) as proc:
        proc.send_signal(signum)
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err[-2000:]
    meta = json.loads((take_dir / "take.json").read_text())
    assert meta["status"] == "interrupted" and meta["reason"] == f"stopped by {signal.Signals(signum).name}" + (
        " (Ctrl-C)" if signum == signal.SIGINT else "")
    assert "interrupted" in out
    counts = check_readable(take_dir)
    ids, exposure, dropped = truth(take_dir)
    for c, cam in enumerate(ids):   # every frame that reached the host before the signal is kept
        assert counts[cam] == int(((exposure[c] >= 0) & ~dropped[c]).sum())
    assert 20 <= sum(counts.values()) < 3 * 7200
    assert load_session(tmp_path / "s").take("t")["status"] == "interrupted"


@pytest.mark.faults
def test_sigkill_leaves_every_written_frame_readable_and_recover_finishes_the_take(tmp_path):
    take_dir = tmp_path / "s" / "t"
    with recording(sim_rig(), tmp_path) as proc:
        proc.kill()
        proc.communicate(timeout=30)
    assert json.loads((take_dir / "take.json").read_text())["status"] == "recording"
    assert (take_dir / ".reserve").exists()
    runner = CliRunner()
    report = runner.invoke(cli, ["sync-report", str(take_dir)])
    assert "killed" in report.output, report.output
    done = runner.invoke(cli, ["recover", str(take_dir)])
    assert done.exit_code == 0, done.output
    meta = json.loads((take_dir / "take.json").read_text())
    counts = check_readable(take_dir, killed=True)   # every row has its packet, every packet decodes
    assert meta["status"] == "interrupted" and "killed" in meta["reason"]
    assert {c["id"]: c["frames"] for c in meta["cameras"]} == counts and sum(counts.values()) >= 60
    assert meta["frames"] == sum(counts.values()) and not (take_dir / ".reserve").exists()
    assert load_session(tmp_path / "s").take("t")["status"] == "interrupted"
    again = runner.invoke(cli, ["recover", str(take_dir)])
    assert again.exit_code == 2 and "nothing to recover" in again.output


def test_refuses_to_start_without_disk_and_existing_takes(tmp_path, monkeypatch):
    rig_file = write_rig(sim_rig(), tmp_path / "rig.toml")
    args = ["record", "--rig", str(rig_file), "--session", str(tmp_path / "s"), "--take", "t",
            "--kind", "calibration", "--duration", "60"]
    usage = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage._replace(free=int(1.03e9)))
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 2 and "not enough free disk" in res.output and "min_free_gb 1 GB" in res.output
    assert not (tmp_path / "s").exists()
    monkeypatch.undo()
    (tmp_path / "s" / "t").mkdir(parents=True)
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 2 and "take exists; use --force" in res.output


def test_session_keeps_one_rig_configuration(tmp_path):
    rig = sim_rig()
    record_take(rig, tmp_path / "s", "a", "calibration", 0.05, RecordOptions(use_leds=False))
    other = dataclasses.replace(rig, fps=60.0)
    with pytest.raises(ValueError, match="recorded with another rig configuration.*fps = 120.0"):
        record_take(other, tmp_path / "s", "b", "calibration", 0.05, RecordOptions(use_leds=False))


def test_flash_offsets_fit_the_take():
    assert flash_offsets(3.0, 50, 1.0) == pytest.approx([0.475, 1.475, 2.475])
    assert flash_offsets(0.3, 30, 1.0) == pytest.approx([0.135])       # shorter than a window: its middle
    assert flash_offsets(0.02, 30, 1.0) == []


def test_stop_flag_keeps_the_first_reason():
    stop = StopFlag()
    stop.set("disk full")
    stop.set("stopped by SIGTERM", by_signal=True)
    assert stop.reason == "disk full" and not stop.by_signal
    from_handler = StopFlag()
    from_handler.signal("stopped by SIGINT (Ctrl-C)")        # no lock taken in the handler ...
    assert from_handler.requested and from_handler.wait(0.0)  # ... the next look turns it into the stop
    assert from_handler.reason == "stopped by SIGINT (Ctrl-C)" and from_handler.by_signal
