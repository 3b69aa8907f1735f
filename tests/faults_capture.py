"""Faults of the capture room for the fault battery: rig.toml and other configuration files,
recording (signals, SIGKILL, a full disk, a lost camera, a failing writer) and the LED controller."""

from __future__ import annotations

import dataclasses
import json
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from faults_kit import (
    SHARED,
    Outcome,
    copy_take,
    fault,
    invoke,
    outcome,
    proc_outcome,
    readable,
    rig_doc,
    run,
    said,
    sim_rig,
    write_doc,
)

from rig.leds import SimulatedLedController, now_ns

# --- rig.toml and other configuration files ----------------------------------------------------------

def _bad_rig(tmp: Path, edit: Callable[[dict], None]) -> Path:
    doc = rig_doc()
    edit(doc)
    return write_doc(doc, tmp / "rig.toml")


def _rig_check(edit: Callable[[dict], None], *needles: str) -> Callable[[Path], Outcome]:
    def check(tmp: Path) -> Outcome:
        res = invoke("rig", "check", _bad_rig(tmp, edit))
        return outcome(res, 2, "rig.toml", *needles)
    return check


def _cam(doc: dict, key: str, value) -> None:
    doc["cameras"][0][key] = value


def _sim_cam(doc: dict, key: str, value) -> None:
    doc["cameras"][0].setdefault("sim", {})[key] = value


for _what, _edit, _key in [
    ("fps = -30", lambda d: d["rig"].__setitem__("fps", -30.0), "fps"),
    ("fps = inf", lambda d: d["rig"].__setitem__("fps", float("inf")), "fps"),
    ("fps = nan", lambda d: d["rig"].__setitem__("fps", float("nan")), "fps"),
    ("a camera's width = 1e9", lambda d: _cam(d, "width", 1_000_000_000), "width"),
    ("jpeg_quality = 900", lambda d: d["storage"].__setitem__("jpeg_quality", 900), "jpeg_quality"),
    ("LED level = 5", lambda d: d["leds"].__setitem__("level", 5.0), "level"),
    ("min_free_gb = -5", lambda d: d["storage"].__setitem__("min_free_gb", -5.0), "min_free_gb"),
    ("simulated drop_rate = 2.0", lambda d: _sim_cam(d, "drop_rate", 2.0), "drop_rate"),
    ("simulated hfov_deg = 0", lambda d: _sim_cam(d, "hfov_deg", 0.0), "hfov_deg"),
    ("sim supersample = -1", lambda d: d["sim"].__setitem__("supersample", -1), "supersample"),
    ("two cameras with one id", lambda d: _cam(d, "id", d["cameras"][1]["id"]), "id"),
]:
    fault("rig.toml", f"`rig check` of {_what}")(_rig_check(_edit, _key))


@fault("rig.toml", "`rig check` of six V4L2 cameras all at CHANGE-ME (rig init's placeholder)")
def _placeholders(tmp: Path) -> Outcome:
    made = invoke("rig", "init", "--layout", "cube53", "--backend", "v4l2", "--cameras", "6", "-o", tmp / "rig.toml")
    if made.exit_code != 0:
        return Outcome(False, f"rig init failed: {said(made)}")
    return outcome(invoke("rig", "check", tmp / "rig.toml"), 2, "CHANGE-ME")


@fault("rig.toml", "`rig check` of a file that is not TOML")
def _not_toml(tmp: Path) -> Outcome:
    (tmp / "rig.toml").write_text("[rig\nfps = 30\n")
    return outcome(invoke("rig", "check", tmp / "rig.toml"), 2, "rig.toml")


@fault("rig.toml", "`record` with fps = nan: refused before any camera opens")
def _record_nan(tmp: Path) -> Outcome:
    rig = _bad_rig(tmp, lambda d: d["rig"].__setitem__("fps", float("nan")))
    res = run("record", "--rig", rig, "--session", tmp / "S", "--take", "t", "--kind", "grasp", "--duration", "1",
              "--no-leds")
    return proc_outcome(res, 2, "fps", check=not (tmp / "S" / "t").exists())


@fault("rig.toml", "`record` with simulated drop_rate = 2.0")
def _record_drop(tmp: Path) -> Outcome:
    rig = _bad_rig(tmp, lambda d: _sim_cam(d, "drop_rate", 2.0))
    res = run("record", "--rig", rig, "--session", tmp / "S", "--take", "t", "--kind", "grasp", "--duration", "1",
              "--no-leds", timeout=60)
    return proc_outcome(res, 2, "drop_rate", check=not (tmp / "S" / "t").exists())


@fault("config", "board.toml with cols = 1")
def _board(tmp: Path) -> Outcome:
    (tmp / "board.toml").write_text('type = "chessboard"\ncols = 1\nrows = 6\nsquare = 0.025\n')
    images = sorted(SHARED.glob("opencv_stereo_chessboard/left0*.jpg"))[:2]
    res = invoke("calibrate", "intrinsics", *images, "--board", tmp / "board.toml", "-o", tmp / "c.json")
    return outcome(res, 2, "board.toml", "cols")


@fault("config", "a subject file in millimetres (bone lengths of 20-50)")
def _subject_mm(tmp: Path) -> Outcome:
    take = copy_take(tmp)
    from dataset_tools.hand.bones import BoneLengths, save_subject
    from manus_core.skeleton import DEFAULT_BONE_LENGTHS

    mm = np.asarray(DEFAULT_BONE_LENGTHS) * 1000   # written in millimetres by another tool
    save_subject(tmp / "s1.json", "s1", BoneLengths(mm, np.zeros(20), np.full(20, 50)))
    res = invoke("annotate", take, "--calib", tmp / "calib", "--keypoints", "simulated", "--bones", tmp / "s1.json",
                 "-o", tmp / "D.h5")
    return outcome(res, 2, "s1.json", check=not (tmp / "D.h5").exists())


@fault("config", "tags.json naming the same tag twice")
def _tags(tmp: Path) -> Outcome:
    square = [[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0], [0, 0.1, 0]]
    (tmp / "tags.json").write_text(json.dumps({"family": "tag36h11", "size": 0.1, "tags": {
        "3": square, "03": [[x + 0.5, y, z] for x, y, z in square]}}))
    take = copy_take(tmp, "calibration")
    res = invoke("calibrate", "rig", take, "--tags", tmp / "tags.json", "--intrinsics", tmp / "calib" / "cameras.json",
                 "-o", tmp / "out")
    return outcome(res, 2, "tags.json", "tags.03")


# --- recording ---------------------------------------------------------------------------------------

def _record_then(tmp: Path, act: Callable[[subprocess.Popen], None], duration: float = 60) -> tuple[int, str, Path]:
    rig = write_doc(rig_doc(), tmp / "rig.toml")
    take = tmp / "S" / "t"
    with open(tmp / "out", "w") as out:
        proc = subprocess.Popen([sys.executable, "-m", "manus_capture.cli", "record", "--rig", str(rig), "--session",
                                 str(tmp / "S"), "--take", "t", "--kind", "calibration", "--duration", str(duration),
                                 "--no-leds"], stdout=out, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                csv = take / "frames.csv"
                if csv.exists() and csv.read_text().count("\n") > 40:
                    break
                time.sleep(0.05)
            act(proc)
            proc.wait(timeout=60)
        finally:
            proc.kill()
    return proc.returncode, (tmp / "out").read_text(), take


def _status(take: Path) -> str:
    return json.loads((take / "take.json").read_text()).get("status", "")


for _sig in (signal.SIGINT, signal.SIGTERM):
    def _signalled(tmp: Path, sig=_sig) -> Outcome:
        code, out, take = _record_then(tmp, lambda p: p.send_signal(sig))
        ok = code == 130 and "Traceback" not in out and _status(take) == "interrupted" and readable(take)
        return Outcome(ok, f"exit {code}: take {_status(take)}, {'readable' if readable(take) else 'NOT readable'}")
    fault("record", f"{signal.Signals(_sig).name} mid-take")(_signalled)


@fault("record", "SIGKILL mid-take, then `sync-report` and `recover`")
def _killed(tmp: Path) -> Outcome:
    code, out, take = _record_then(tmp, lambda p: p.kill())
    report = invoke("sync-report", take)
    recover = invoke("recover", take)
    ok = ("killed" in report.output and recover.exit_code == 0 and _status(take) == "interrupted"
          and not (take / ".reserve").exists() and readable(take))
    return Outcome(ok, f"sync-report: {said(report)} / recover: exit {recover.exit_code}: {said(recover)}")


@fault("record", "the disk fills up mid-take (tmpfs)")
def _full_disk(tmp: Path) -> Outcome:
    disk = tmp / "disk"
    disk.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=96m", "tmpfs", str(disk)], capture_output=True).returncode:
        return Outcome(False, "not run: cannot mount a tmpfs here")
    try:
        doc = rig_doc()
        doc["storage"]["min_free_gb"] = 0.0
        rig = write_doc(doc, tmp / "rig.toml")
        with open(tmp / "out", "w") as out:
            proc = subprocess.Popen([sys.executable, "-m", "manus_capture.cli", "record", "--rig", str(rig),
                                     "--session", str(disk / "S"), "--take", "t", "--kind", "calibration",
                                     "--duration", "20", "--no-leds"], stdout=out, stderr=subprocess.STDOUT)
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and not (disk / "S" / "t" / "frames.csv").exists():
                time.sleep(0.05)
            time.sleep(0.5)
            subprocess.run(["dd", "if=/dev/zero", f"of={disk / 'fill'}", "bs=1M"], capture_output=True)
            code = proc.wait(timeout=60)
        (disk / "fill").unlink()
        take = disk / "S" / "t"
        text = (tmp / "out").read_text()
        ok = code == 1 and "disk full" in text and _status(take) == "interrupted" and readable(take)
        return Outcome(ok, f"exit {code}: take {_status(take)}: {json.loads((take / 'take.json').read_text())['reason']}")
    finally:
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)


def _record_api(tmp: Path, wrap_camera=None, patch_writer=None):
    """record_take with a camera or a writer that fails (the faults a backend or a disk makes)."""
    from rig.backends import BACKENDS
    from rig.mkv import MkvWriter
    from rig.record import RecordOptions, record_take

    inner = BACKENDS["sim"]
    saved_write = MkvWriter.write
    if wrap_camera is not None:
        def open_take(setup):
            opened = inner.open(setup)
            return dataclasses.replace(opened, cameras={k: wrap_camera(k, v) for k, v in opened.cameras.items()})
        BACKENDS["sim"] = dataclasses.replace(inner, open=open_take)
    if patch_writer is not None:
        MkvWriter.write = patch_writer(saved_write)
    try:
        return record_take(sim_rig(), tmp / "S", "t", "calibration", 0.5, RecordOptions(use_leds=False))
    finally:
        BACKENDS["sim"] = inner
        MkvWriter.write = saved_write


@fault("record", "a camera unplugged mid-take")
def _lost_camera(tmp: Path) -> Outcome:
    from manus_core.errors import CameraDisconnected

    class Unplugged:
        def __init__(self, cam) -> None:
            self.cam, self.n = cam, 0

        def read(self, timeout_s: float = 1.0):
            self.n += 1
            if self.n > 10:
                raise CameraDisconnected("camera unplugged")
            return self.cam.read(timeout_s)

        def __getattr__(self, name):
            return getattr(self.cam, name)

    lost = sim_rig().cameras[1].id
    result = _record_api(tmp, wrap_camera=lambda cid, cam: Unplugged(cam) if cid == lost else cam)
    meta = json.loads((tmp / "S" / "t" / "take.json").read_text())
    ok = result.exit_code == 1 and meta["lost_cameras"] == [lost] and readable(tmp / "S" / "t")
    return Outcome(ok, f"exit {result.exit_code}: lost {meta['lost_cameras']}")


@fault("record", "a video writer fails (EIO) mid-take")
def _writer_crash(tmp: Path) -> Outcome:
    import errno

    def failing(real):
        def write(self, jpegs):
            if self.frames + len(jpegs) > 12:
                raise OSError(errno.EIO, "Input/output error")
            real(self, jpegs)
        return write

    result = _record_api(tmp, patch_writer=failing)
    meta = json.loads((tmp / "S" / "t" / "take.json").read_text())
    ok = result.exit_code == 1 and meta["status"] == "interrupted" and readable(tmp / "S" / "t")
    return Outcome(ok, f"exit {result.exit_code}: {meta['status']}: {meta['reason'][:80]}")


# --- LEDs --------------------------------------------------------------------------------------------

def _led_rig(tmp: Path, port: str) -> Path:
    doc = rig_doc()
    doc["leds"].update(port=port, protocol="ascii", panels=3)
    return write_doc(doc, tmp / "rig.toml")


@fault("leds", "`leds on`, then `leds set 0.3` in another process, on one controller")
def _led_sessions(tmp: Path) -> Outcome:
    with SimulatedLedController(panels=3, link_dir=tmp) as sim:
        rig = _led_rig(tmp, sim.path)
        first, second = run("leds", "on", "--rig", rig), run("leds", "set", "0.3", "--rig", rig)
        levels = sim.state_at(now_ns()).tolist()
    ok = first.returncode == 0 and second.returncode == 0 and levels == [0.3] * 3
    return Outcome(ok, f"exit {first.returncode}, {second.returncode}: the panels are at {levels}")


@fault("leds", "`leds on` on a port where no controller is")
def _led_absent(tmp: Path) -> Outcome:
    return proc_outcome(run("leds", "on", "--rig", _led_rig(tmp, str(tmp / "ttyNONE"))), 1, "ttyNONE")


@fault("leds", "the LED controller unplugged mid-take, not back")
def _led_lost(tmp: Path) -> Outcome:
    with SimulatedLedController(panels=3, link_dir=tmp) as sim:
        rig = _led_rig(tmp, sim.path)
        take = tmp / "S" / "t"

        def unplug() -> None:   # as the first flash starts, and for good
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and "FLASH" not in [verb for _, verb in sim.executed()]:
                time.sleep(0.001)
            sim.unplug()

        thread = threading.Thread(target=unplug)
        thread.start()
        res = run("record", "--rig", rig, "--session", tmp / "S", "--take", "t", "--kind", "calibration",
                  "--duration", "0.9", "--flash-ms", "200", "--flash-every", "0.3")
        thread.join()
    return proc_outcome(res, 1, sim.path, check=readable(take))
