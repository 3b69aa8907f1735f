"""Faults of the offline stages for the fault battery: bad takes under sync-report, DATASET.h5
across stages, outputs on a full or read-only disk, and partial calibrations."""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
from faults_kit import SHARED, Outcome, copy_take, fault, invoke, outcome, rig_doc, said, sim_rig, write_doc

from manus_core.take import Take

# --- sync-report on bad takes -------------------------------------------------------------------------

def _sync(tmp: Path, harm: Callable[[Path], None], code: int, *needles: str) -> Outcome:
    take = copy_take(tmp)
    harm(take)
    return outcome(invoke("sync-report", take, "--force"), code, *needles)


def _first_cam(take: Path) -> str:
    return Take(take).cameras[0]


def _truncate(take: Path) -> None:
    video = take / "cams" / f"{_first_cam(take)}.mkv"
    video.write_bytes(video.read_bytes()[: video.stat().st_size // 2])


def _empty(take: Path) -> None:
    (take / "cams" / f"{_first_cam(take)}.mkv").write_bytes(b"")


def _drop_rows(take: Path, n: int = 3) -> None:
    lines = (take / "frames.csv").read_text().splitlines(keepends=True)
    cam = _first_cam(take)
    mine = [i for i, line in enumerate(lines) if line.startswith(cam + ",")]
    (take / "frames.csv").write_text("".join(line for i, line in enumerate(lines) if i not in set(mine[-n:])))


def _ghost_rows(take: Path) -> None:
    lines = (take / "frames.csv").read_text().splitlines(keepends=True)
    ghost = ["ghost" + line[line.index(","):] for line in lines[1:4]]
    (take / "frames.csv").write_text("".join(lines + ghost))


def _recording(take: Path) -> None:
    meta = json.loads((take / "take.json").read_text())
    meta["status"] = "recording"
    meta.pop("recorder", None)
    (take / "take.json").write_text(json.dumps(meta))


fault("sync", "a video cut in half")(lambda tmp: _sync(tmp, _truncate, 1, ".mkv"))
fault("sync", "an empty video")(lambda tmp: _sync(tmp, _empty, 1, ".mkv"))
fault("sync", "frames.csv shorter than its video")(lambda tmp: _sync(tmp, _drop_rows, 1, "frames.csv"))
fault("sync", "frames.csv rows of a camera the take does not have")(lambda tmp: _sync(tmp, _ghost_rows, 1, "ghost"))
fault("sync", "a take.json left at status 'recording'")(lambda tmp: _sync(tmp, _recording, 1, "killed"))


@fault("sync", "a take of rig init's default rig (free-run): verdict")
def _free_run(tmp: Path) -> Outcome:
    made = invoke("rig", "init", "--layout", "cube53", "--cameras", "8", "--resolution", "64x36", "--fps", "30",
                  "-o", tmp / "rig.toml")
    rec = invoke("record", "--rig", tmp / "rig.toml", "--session", tmp / "S", "--take", "t", "--kind",
                 "calibration", "--duration", "1", "--no-leds")
    if made.exit_code or rec.exit_code:
        return Outcome(False, f"could not record: {said(made)} {said(rec)}")
    return outcome(invoke("sync-report", tmp / "S" / "t", "--force"), 0)


@fault("sync", "drops at the end of a software-triggered take: counted against the truth")
def _end_drops(tmp: Path) -> Outcome:
    from manus_core.ground_truth import GroundTruth

    found = 0
    for seed in range(2, 12):   # a take in which some camera's last frame was dropped
        rig = sim_rig(seed)
        rig = dataclasses.replace(rig, sync="software-trigger", cameras=tuple(
            dataclasses.replace(c, sim=dataclasses.replace(c.sim, drop_rate=0.2)) for c in rig.cameras))
        shutil.rmtree(tmp / "S", ignore_errors=True)
        write_doc(rig_doc(rig), tmp / "rig.toml")
        invoke("record", "--rig", tmp / "rig.toml", "--session", tmp / "S", "--take", "t", "--kind", "calibration",
               "--duration", "0.5", "--no-leds")
        dropped = GroundTruth.of_take(tmp / "S" / "t").frames.dropped
        if dropped[:, -1].any():
            found = seed
            break
    if not found:
        return Outcome(False, "not run: no seed dropped a last frame")
    res = invoke("sync-report", tmp / "S" / "t", "--force")
    report = json.loads((tmp / "S" / "t" / "sync_report.json").read_text())
    counted = sum(int(c.get("frames_dropped", 0)) for c in report["cameras"].values()) \
        if isinstance(report["cameras"], dict) else sum(int(c.get("frames_dropped", 0)) for c in report["cameras"])
    truth = int(dropped.sum())
    return Outcome(counted == truth and "Traceback" not in res.output, f"{counted} drops counted, {truth} true")


@fault("sync", "a folder that is not a take")
def _not_a_take(tmp: Path) -> Outcome:
    (tmp / "x").mkdir()
    return outcome(invoke("sync-report", tmp / "x"), 2, "take.json")


@fault("sync", "frames.csv with a torn line")
def _torn_csv(tmp: Path) -> Outcome:
    def harm(take: Path) -> None:
        with open(take / "frames.csv", "a") as f:
            f.write("x+11,12,34")
    return _sync(tmp, harm, 2, "frames.csv", "line")


# --- DATASET.h5 ----------------------------------------------------------------------------------------

def _annotate(take: Path, out: Path, *args: object):
    return invoke("annotate", take, "--calib", take.parents[1] / "calib", "--keypoints", "simulated", "-o", out,
                  *args)


def _add_masks(path: Path, key: str) -> None:
    """What segment writes: masks of a few frame groups under the take's group."""
    with h5py.File(path, "a") as f:
        f.attrs.setdefault("format", "manus-capture dataset")
        f.attrs.setdefault("version", 1)
        group = f.require_group(key)
        group.attrs["manus_take"] = True
        for name in ("masks/hand", "masks/object"):
            group.create_dataset(name, data=np.ones((2, 3, 4, 4), bool))
        group.create_dataset("masks/frame_ns", data=np.arange(2))
        group.create_dataset("paint/masks", data=np.ones((3, 4, 4), bool))


def _has_masks(path: Path, key: str) -> bool:
    with h5py.File(path, "r") as f:
        return f"{key}/masks/hand" in f and f"{key}/paint/masks" in f


@fault("dataset", "`stats` of a dataset with a take that was segmented, not annotated")
def _stats_segment_only(tmp: Path) -> Outcome:
    _add_masks(tmp / "D.h5", "S/t")
    return outcome(invoke("stats", tmp / "D.h5"), 0)


@fault("dataset", "`annotate --force` of a take that has masks and paint")
def _force_keeps_masks(tmp: Path) -> Outcome:
    take = copy_take(tmp)
    first = _annotate(take, tmp / "D.h5")
    _add_masks(tmp / "D.h5", "S/t")
    res = _annotate(take, tmp / "D.h5", "--force")
    return outcome(res, 0, check=first.exit_code == 0 and _has_masks(tmp / "D.h5", "S/t"))


@fault("dataset", "`annotate` of a take that holds only segment output")
def _annotate_segment_only(tmp: Path) -> Outcome:
    take = copy_take(tmp)
    _add_masks(tmp / "D.h5", "S/t")
    res = _annotate(take, tmp / "D.h5")
    return outcome(res, 0, check=not (tmp / ".D.h5.parts").exists() and _has_masks(tmp / "D.h5", "S/t"))


@fault("dataset", "`annotate` after the take was re-recorded with `record --force`")
def _rerecorded(tmp: Path) -> Outcome:
    take = copy_take(tmp)
    first = _annotate(take, tmp / "D.h5")
    rig = write_doc(rig_doc(), tmp / "rig.toml")
    invoke("record", "--rig", rig, "--session", tmp / "S", "--take", "t", "--kind", "grasp", "--duration", "1.5",
           "--no-leds", "--force")
    res = _annotate(take, tmp / "D.h5")
    with h5py.File(tmp / "D.h5", "r") as f:
        groups = len(f["S/t/frame_ns"])
    frames = max(Take(take).frame_count(c) for c in Take(take).cameras)
    return Outcome(first.exit_code == 0 and res.exit_code == 0 and groups >= frames - 1,
                   f"exit {res.exit_code}: {groups} frame groups in DATASET.h5, {frames} frames per camera")


@fault("dataset", "`annotate` with another calibration")
def _other_calib(tmp: Path) -> Outcome:
    take = copy_take(tmp)
    _annotate(take, tmp / "D.h5")
    shutil.copytree(tmp / "calib", tmp / "calib2")
    cams = json.loads((tmp / "calib2" / "cameras.json").read_text())
    (tmp / "calib2" / "cameras.json").write_text(json.dumps(cams, indent=2))   # other bytes, same cameras
    res = invoke("annotate", take, "--calib", tmp / "calib2", "--keypoints", "simulated", "-o", tmp / "D.h5")
    with h5py.File(tmp / "D.h5", "r") as f:
        used = f["S/t"].attrs.get("calibration", "")
    return Outcome(res.exit_code == 0 and str(tmp / "calib2") in str(used), f"exit {res.exit_code}: calibration "
                   f"attribute {used}")


@fault("dataset", "`contacts` on a take that has no annotation")
def _contacts_missing(tmp: Path) -> Outcome:
    _add_masks(tmp / "D.h5", "S/t")
    for name in ("hand.pt", "object.pt"):
        (tmp / name).write_bytes(b"not a model")
    res = invoke("contacts", tmp / "D.h5", "--take", "S/t", "--hand", tmp / "hand.pt", "--object", tmp / "object.pt")
    return outcome(res, 2, "S/t")


@fault("dataset", "`stats` of a file that is not HDF5")
def _stats_garbage(tmp: Path) -> Outcome:
    (tmp / "D.h5").write_bytes(b"garbage" * 10)
    return outcome(invoke("stats", tmp / "D.h5"), 2, "D.h5")


# --- writing outputs -------------------------------------------------------------------------------

def _mounted(tmp: Path, size: str = "4m", readonly: bool = False) -> Path | None:
    disk = tmp / "disk"
    disk.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(disk)],
                      capture_output=True).returncode:
        return None
    if readonly:
        subprocess.run(["mount", "-o", "remount,ro", str(disk)], check=True)
    else:
        subprocess.run(["dd", "if=/dev/zero", f"of={disk / 'fill'}", "bs=64k"], capture_output=True)
    return disk


def _on_disk(readonly: bool, build: Callable[[Path, Path], object]) -> Callable[[Path], Outcome]:
    def check(tmp: Path) -> Outcome:
        disk = _mounted(tmp, readonly=readonly)
        if disk is None:
            return Outcome(False, "not run: cannot mount a tmpfs here")
        try:
            before = sorted(p.name for p in disk.rglob("*"))
            res = build(tmp, disk)
            after = sorted(p.name for p in disk.rglob("*"))
            return outcome(res, 1, str(disk), check=before == after)
        finally:
            subprocess.run(["umount", "-l", str(disk)], capture_output=True)
    return check


@fault("output", "`sync-report` of a take on a disk that is full")
def _sync_full(tmp: Path) -> Outcome:
    take = copy_take(tmp)
    disk = tmp / "disk"
    disk.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(disk)], capture_output=True).returncode:
        return Outcome(False, "not run: cannot mount a tmpfs here")
    try:
        for name in ("sync_report.json", "sync_report.md", "sync_timeline.png", "frame_groups.npz"):
            (take / name).unlink(missing_ok=True)
        shutil.copytree(take, disk / "t")
        subprocess.run(["dd", "if=/dev/zero", f"of={disk / 'fill'}", "bs=64k"], capture_output=True)
        before = sorted(p.name for p in disk.rglob("*"))
        res = invoke("sync-report", disk / "t", "--force")
        return outcome(res, 1, str(disk), check=before == sorted(p.name for p in disk.rglob("*")))
    finally:
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)


def _stats_plot(tmp: Path, disk: Path):
    take = copy_take(tmp)
    _annotate(take, tmp / "D.h5")
    return invoke("stats", tmp / "D.h5", "--plot", disk / "out" / "plot.png")


def _annotate_to(tmp: Path, disk: Path):
    take = copy_take(tmp)
    return _annotate(take, disk / "out" / "D.h5")


fault("output", "`stats --plot` onto a full disk")(_on_disk(False, _stats_plot))
fault("output", "`annotate -o` onto a full disk")(_on_disk(False, _annotate_to))
fault("output", "`annotate -o` onto a read-only file system")(_on_disk(True, _annotate_to))
fault("output", "`stats --plot` onto a read-only file system")(_on_disk(True, _stats_plot))


# --- partial calibration -------------------------------------------------------------------------------

@fault("calibration", "`calibrate rig --allow-partial` with one camera's video unreadable")
def _partial_calibrate(tmp: Path) -> Outcome:
    videos = tmp / "session"
    videos.mkdir()
    for c in range(3):
        (videos / f"cam{c}.mp4").symlink_to(SHARED / f"caliscope_4cam_charuco/calibration/extrinsic/cam_{c}.mp4")
    (videos / "cam3.mp4").write_bytes(b"\x00garbage" * 500)
    (tmp / "board.toml").write_text('type = "charuco"\ncols = 4\nrows = 5\nsquare = 0.054\nmarker = 0.0405\n'
                                    'dictionary = "DICT_4X4_1000"\ninverted = true\n')
    res = invoke("calibrate", "rig", videos, "--board", tmp / "board.toml", "--board-frames", "6", "--workers", "1",
                 "--allow-partial", "-o", tmp / "out")
    return outcome(res, 0, "cam3", check=(tmp / "out" / "cameras.json").exists())


@fault("calibration", "`annotate` with a calibration that lacks one of the take's cameras")
def _partial_annotate(tmp: Path) -> Outcome:
    take = copy_take(tmp)
    cams = json.loads((tmp / "calib" / "cameras.json").read_text())
    first = _first_cam(take)
    if isinstance(cams.get("cameras"), dict):
        cams["cameras"].pop(first)
    else:
        cams["cameras"] = [c for c in cams["cameras"] if c.get("id") != first]
    (tmp / "calib" / "cameras.json").write_text(json.dumps(cams))
    return outcome(_annotate(take, tmp / "D.h5"), 0, first)
