"""The take's video files (rig.mkv): readable when the recorder is killed, failed writes rolled back,
seekable, and clean to the reference demuxer."""

from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from rig.mkv import MkvWriter


def test_mkv_is_readable_when_killed_and_rolls_back_failed_writes(tmp_path, monkeypatch):
    frames = []
    for k in range(40):
        img = np.full((32, 48, 3), 6 * k, np.uint8)
        frames.append(cv2.imencode(".jpg", img)[1].tobytes())

    w = MkvWriter(tmp_path / "a.mkv", 48, 32, 120.0, cluster_frames=16)
    for f in frames:
        w.write(f)
    # a process killed here leaves the file without sizes, cues or duration
    shutil.copy(tmp_path / "a.mkv", tmp_path / "killed.mkv")
    assert _packets(tmp_path / "killed.mkv") == frames
    size = os.path.getsize(tmp_path / "killed.mkv")
    os.truncate(tmp_path / "killed.mkv", size - 200)        # killed in the middle of a block
    assert _packets(tmp_path / "killed.mkv") == frames[:39]
    # a write that fails half-way is cut back to the previous frame
    real_writev = os.writev

    def half_then_full(fd, parts):
        real_writev(fd, [b"".join(parts)[:300]])
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("rig.mkv.os.writev", half_then_full)
    with pytest.raises(OSError, match="No space left"):
        w.write(frames[0])
    monkeypatch.undo()
    assert w.frames == 40
    w.write(frames[0])
    w.rollback()        # ... and a frame whose frames.csv row could not be written is removed
    w.close()
    assert _packets(tmp_path / "a.mkv") == frames
    cap = cv2.VideoCapture(str(tmp_path / "a.mkv"))
    assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(120.0, rel=1e-6)
    assert cap.set(cv2.CAP_PROP_POS_FRAMES, 30)              # cues: seek by frame index
    ok, img = cap.read()
    assert ok and abs(int(img[0, 0, 0]) - 6 * 30) <= 2
    if shutil.which("ffprobe"):   # the reference demuxer finds nothing to complain about
        probe = subprocess.run(["ffprobe", "-v", "error", "-count_packets", "-show_entries",
                                "stream=nb_read_packets,codec_name", "-of", "json", str(tmp_path / "a.mkv")],
                               capture_output=True, text=True, check=True)
        stream = json.loads(probe.stdout)["streams"][0]
        assert stream == {"codec_name": "mjpeg", "nb_read_packets": "40"} and probe.stderr == ""


def _packets(path: Path) -> list[bytes]:
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG, [cv2.CAP_PROP_FORMAT, -1])
    out = []
    while True:
        ok, p = cap.read()
        if not ok:
            return out
        out.append(p.reshape(-1).tobytes())
