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

from manus_core.matroska import MatroskaVideo, count_frames
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


def _write(path: Path, frames: list[bytes], cluster_frames: int, close: bool = True) -> None:
    w = MkvWriter(path, 48, 32, 120.0, cluster_frames=cluster_frames, fsync=False)
    for f in frames:
        w.write(f)
    if close:
        w.close()
    else:   # a recorder killed here: no sizes, no Cues
        os.close(w._fd)
        w._fd = None


@pytest.fixture(scope="module")
def jpegs() -> list[bytes]:
    # each of its own grey and quality (so its own size): a packet off by one shows
    return [cv2.imencode(".jpg", np.full((32, 48, 3), (5 * k) % 256, np.uint8),
                         [cv2.IMWRITE_JPEG_QUALITY, 50 + k % 40])[1].tobytes() for k in range(300)]


def test_reader_gives_the_reference_demuxers_packets_from_any_frame_through_the_cues(tmp_path, jpegs, monkeypatch):
    path = tmp_path / "a.mkv"
    _write(path, jpegs, cluster_frames=20)
    assert [p.tobytes() for p in MatroskaVideo(path).packets()] == _packets(path) == jpegs
    assert count_frames(path) == (300, None)
    reads = []
    real = MatroskaVideo._header

    def counted(self, pos):
        reads.append(pos)
        return real(self, pos)

    monkeypatch.setattr(MatroskaVideo, "_header", counted)
    with MatroskaVideo(path) as video:
        assert [c[0] for c in video.cues] == list(range(0, 300, 20))
        opened = len(reads)
        first = next(video.packets(277))
        # the Cues lead to frame 260's cluster: its header, the Timestamp and 18 blocks, not 277 blocks
        assert len(reads) - opened <= 22
    assert first.tobytes() == jpegs[277]


def test_reader_walks_a_killed_recorders_file_without_cues_up_to_its_last_whole_frame(tmp_path, jpegs):
    path = tmp_path / "killed.mkv"
    _write(path, jpegs[:100], cluster_frames=16, close=False)
    os.truncate(path, os.path.getsize(path) - 100)          # killed in the middle of frame 100
    with MatroskaVideo(path) as video:
        assert video.cues == []
        assert [p.tobytes() for p in video.packets(90)] == jpegs[90:99]
    assert count_frames(path) == (99, "cut short: ends inside frame 100")


def test_reader_names_what_is_not_a_matroska_file(tmp_path):
    (tmp_path / "empty.mkv").write_bytes(b"")
    (tmp_path / "text.mkv").write_bytes(b"not a video at all")
    assert count_frames(tmp_path / "empty.mkv") == (0, "empty (0 bytes)")
    assert count_frames(tmp_path / "text.mkv") == (0, "not a Matroska file (no EBML header)")
    assert count_frames(tmp_path / "absent.mkv")[1].startswith("cannot be read (No such file")


def test_reading_a_take_in_frame_ranges_grows_linearly_with_its_length(tmp_path, jpegs, monkeypatch):
    """Tasks of 16 frames each (as detect splits a camera) over a take and one twice as long:
    every frame is decoded once, and the element headers walked grow with the take, not with its
    square (each task enters its video through the Cues instead of walking from frame 0)."""
    from manus_core import take as take_module
    from manus_core.take import Take

    headers, decoded = [0], [0]
    real_header, real_decode = MatroskaVideo._header, take_module._decode

    def header(self, pos):
        headers[0] += 1
        return real_header(self, pos)

    def decode(packet, path, k):
        decoded[0] += 1
        return real_decode(packet, path, k)

    monkeypatch.setattr(MatroskaVideo, "_header", header)
    monkeypatch.setattr(take_module, "_decode", decode)
    cost = {}
    for n in (150, 300):
        folder = tmp_path / f"t{n}"
        (folder / "cams").mkdir(parents=True)
        _write(folder / "cams" / "a.mkv", jpegs[:n], cluster_frames=30)
        (folder / "take.json").write_text(json.dumps({"cameras": ["a"], "fps": 120}))
        (folder / "frames.csv").write_text("cam,seq,t_device_ns,t_host_ns,bytes,flags\n" + "".join(
            f"a,{k},{k * 8333333},{k * 8333333 + 1000},{len(jpegs[k])},0\n" for k in range(n)))
        headers[0] = decoded[0] = 0
        take = Take(folder)
        for start in range(0, n, 16):
            stop = min(start + 16, n)
            assert [k for k, _ in take.iter_frames("a", start, stop)] == list(range(start, stop))
        cost[n] = headers[0], decoded[0]
    assert cost[150][1] == 150 and cost[300][1] == 300
    assert cost[300][0] <= 2.2 * cost[150][0], cost     # from frame 0 each time: 3.4x


def test_frames_decoded_into_a_buffer_of_their_size_only():
    """A stage decodes a camera's frames into its frame group's buffer: the same pixels as a frame
    decoded on its own, and a frame of another size is refused naming the file and both sizes."""
    from manus_core.errors import TakeError
    from manus_core.take import _decode

    image = cv2.GaussianBlur(np.random.default_rng(0).integers(0, 256, (48, 64, 3), np.uint8), (0, 0), 2)
    packet = np.frombuffer(cv2.imencode(".jpg", image)[1].tobytes(), np.uint8)
    alone = _decode(packet, Path("cam.mkv"), 3)
    out = np.zeros((48, 64, 3), np.uint8)
    assert _decode(packet, Path("cam.mkv"), 3, out) is out and np.array_equal(out, alone)
    for shape in ((40, 64, 3), (60, 80, 3)):   # too small for the frame, and larger than it
        with pytest.raises(TakeError, match=rf"cam.mkv: frame 3 is 64x48, the take's frames {shape[1]}x{shape[0]}"):
            _decode(packet, Path("cam.mkv"), 3, np.zeros(shape, np.uint8))

