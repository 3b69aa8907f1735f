"""Reading a take's Matroska videos from their element headers: frame counts, and the JPEG
packets from any frame on, found through the Cues the recorder's muxer writes (rig.mkv).

Why not a demuxer library: counting and seeking need only the headers, which are a few bytes every
~100 KB, so a 10 s video of 1280x720 MJPEG is counted without reading its frames, and frame k is
found by one Cue lookup and a walk over at most one cluster's block headers. The file is read
with positioned reads into a small buffer, never mapped: a stage's memory does not grow with the
video's length. One video track per file, no lacing: what MkvWriter and ffmpeg's MJPEG copy write.
A file cut short (a killed recorder, a truncated copy) is read up to its last complete frame.
"""

from __future__ import annotations

import os
from bisect import bisect_right
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np

# Element ids (Matroska specification, RFC 9559)
EBML = 0x1A45DFA3
SEGMENT = 0x18538067
SEEK_HEAD, SEEK, SEEK_ID, SEEK_POSITION = 0x114D9B74, 0x4DBB, 0x53AB, 0x53AC
INFO, TIMESTAMP_SCALE, DURATION, MUXING_APP, WRITING_APP = 0x1549A966, 0x2AD7B1, 0x4489, 0x4D80, 0x5741
TRACKS, TRACK_ENTRY = 0x1654AE6B, 0xAE
CLUSTER, TIMESTAMP, SIMPLE_BLOCK, BLOCK_GROUP, BLOCK = 0x1F43B675, 0xE7, 0xA3, 0xA0, 0xA1
CUES, CUE_POINT, CUE_TIME, CUE_TRACK_POSITIONS, CUE_TRACK, CUE_CLUSTER_POSITION = (
    0x1C53BB6B, 0xBB, 0xB3, 0xB7, 0xF7, 0xF1)
VOID = 0xEC

# a muxer whose block timestamps are frame indices (one tick per frame): only its Cues say which
# frame a cluster starts with; any other file is walked from its first cluster
FRAME_INDEX_MUXER = "manus-capture"
HEADER_MAX = 12   # an element id (<= 4 bytes) and its size (<= 8)


class VideoFrames(NamedTuple):
    """A video's complete frames, and why there may be fewer than were written (None when the
    file ends where its last element does)."""

    frames: int
    problem: str | None


class MatroskaVideo:
    """One Matroska file, opened for reading. ValueError (with the reason) if it is none."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._fd = os.open(self.path, os.O_RDONLY | os.O_CLOEXEC)
        try:
            self.size = os.fstat(self._fd).st_size
            self._open()
        except BaseException:
            os.close(self._fd)
            raise

    def close(self) -> None:
        os.close(self._fd)

    def __enter__(self) -> MatroskaVideo:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- element headers ---------------------------------------------------------------------
    def _header(self, pos: int) -> tuple[int, int | None, int] | None:
        """(id, payload size or None when unknown, payload start) of the element at `pos`; None
        when its header runs past the end of the file; ValueError where no element can start."""
        found = _parse_header(os.pread(self._fd, HEADER_MAX, pos), 0)
        return None if found is None else (found[0], found[1], pos + found[2])

    def _payload(self, data: int, length: int) -> bytes:
        return os.pread(self._fd, length, data)

    def _open(self) -> None:
        try:
            head = self._header(0) if self.size else None
        except ValueError:
            head = None
        if self.size == 0:
            raise ValueError("empty (0 bytes)")
        if head is None or head[0] != EBML or head[1] is None:
            raise ValueError("not a Matroska file (no EBML header)")
        segment = self._header(head[2] + head[1])
        if segment is None or segment[0] != SEGMENT:
            raise ValueError("not a Matroska file (no Segment after the EBML header)")
        self.segment = segment[2]
        self.segment_end = None if segment[1] is None else segment[2] + segment[1]
        self.muxer, self.first_cluster, cues_at = "", None, None
        for eid, length, data in self._top_level():
            if eid == SEEK_HEAD and length is not None:
                cues_at = self._cues_position(self._payload(data, length))
            elif eid == INFO and length is not None:
                muxer = _children(self._payload(data, length)).get(MUXING_APP, b"")
                self.muxer = muxer.decode("utf-8", "replace")
        self.cues = self._read_cues(cues_at) if self.muxer == FRAME_INDEX_MUXER and cues_at is not None else []

    def _top_level(self) -> Iterator[tuple[int, int | None, int]]:
        """The Segment's children up to its first Cluster, whose start goes to first_cluster."""
        pos, end = self.segment, self.segment_end or self.size
        while pos < end:
            try:
                found = self._header(pos)
            except ValueError:
                return
            if found is None:
                return
            eid, length, data = found
            if eid == CLUSTER:
                self.first_cluster = pos
                return
            yield found
            if length is None:
                return
            pos = data + length

    def _cues_position(self, seek_head: bytes) -> int | None:
        for eid, seek in _elements(seek_head):
            fields = _children(seek) if eid == SEEK else {}
            if fields.get(SEEK_ID) == CUES.to_bytes(4, "big") and SEEK_POSITION in fields:
                return self.segment + int.from_bytes(fields[SEEK_POSITION], "big")
        return None

    def _read_cues(self, at: int) -> list[tuple[int, int]]:
        """(frame index, cluster's file offset) of every Cue point, in order; [] when the Cues
        are not where the SeekHead says (a file whose writer died before it wrote them). The Cues
        are read in one piece: a task that opens the video pays one read, however long it is."""
        try:
            found = self._header(at)
        except ValueError:
            return []
        if found is None or found[0] != CUES or found[1] is None or found[2] + found[1] > self.size:
            return []
        cues = []
        for eid, point in _elements(self._payload(found[2], found[1])):
            fields = _children(point) if eid == CUE_POINT else {}
            where = _children(fields.get(CUE_TRACK_POSITIONS, b"")).get(CUE_CLUSTER_POSITION)
            if CUE_TIME in fields and where is not None:
                cues.append((int.from_bytes(fields[CUE_TIME], "big"), self.segment + int.from_bytes(where, "big")))
        return sorted(cues)

    # -- frames ------------------------------------------------------------------------------
    def _blocks(self, pos: int, counted: int) -> Iterator[tuple[int, int]]:
        """(payload start, size) of every complete frame block from `pos` (a cluster's start) on;
        `counted` frames come before it. Where the file stops making sense, self.problem says why."""
        self.problem: str | None = None
        end, frames = self.size, counted
        while pos < end:
            try:
                found = self._header(pos)
            except ValueError:
                self.problem = f"no Matroska element at byte {pos}, after frame {frames}"
                return
            if found is None:
                self.problem = f"cut short: ends inside an element header at byte {pos}"
                return
            eid, length, data = found
            if eid in (CLUSTER, BLOCK_GROUP):
                pos = data      # containers: their children are walked, whether their size is known or not (live)
                continue
            if length is None:
                self.problem = f"element {eid:#x} of unknown size at byte {pos}"
                return
            if data + length > end:
                block = eid in (SIMPLE_BLOCK, BLOCK)
                inside = f"frame {frames + 1}" if block else f"the element at byte {pos} ({eid:#x})"
                self.problem = f"cut short: ends inside {inside}"
                return
            if eid in (SIMPLE_BLOCK, BLOCK):
                yield data, length
                frames += 1
            pos = data + length
        if self.segment_end is not None and self.segment_end > self.size:
            self.problem = f"cut short: {self.segment_end - self.size} bytes fewer than its header says"

    def count(self) -> VideoFrames:
        """The complete frames, counted from the element headers alone."""
        if self.first_cluster is None:
            return VideoFrames(0, None if self.segment_end is not None and self.segment_end <= self.size
                               else "no frames (no Cluster)")
        frames = sum(1 for _ in self._blocks(self.first_cluster, 0))
        return VideoFrames(frames, self.problem)

    def packets(self, start: int = 0) -> Iterator[np.ndarray]:
        """The JPEG packets (1-D uint8) of frames start, start + 1, ... up to the last complete one.
        With Cues, the walk begins at the cluster holding frame `start`; without, at the first."""
        if self.first_cluster is None:
            return
        pos, k = self.first_cluster, 0
        i = bisect_right(self.cues, (start, float("inf"))) - 1
        if start > 0 and i >= 0:
            k, pos = self.cues[i]
        for data, length in self._blocks(pos, k):
            if k >= start:
                block = self._payload(data, length)
                track_len = 9 - block[0].bit_length()       # track number (vint), timecode (2), flags (1)
                yield np.frombuffer(block, np.uint8, offset=track_len + 3)
            k += 1


def _parse_header(buf: bytes, pos: int) -> tuple[int, int | None, int] | None:
    """(id, payload size or None when unknown, payload start) of the element at buf[pos]; None
    when the header runs past the buffer; ValueError where no element can start."""
    if pos >= len(buf):
        return None
    id_len = 9 - buf[pos].bit_length()          # leading zero bits + 1
    if id_len > 4:
        raise ValueError(pos)
    if pos + id_len >= len(buf):
        return None
    size_len = 9 - buf[pos + id_len].bit_length()
    if size_len > 8:
        raise ValueError(pos)
    data = pos + id_len + size_len
    if data > len(buf):
        return None
    value = int.from_bytes(buf[pos + id_len:data], "big") & ((1 << (7 * size_len)) - 1)
    length = None if value == (1 << (7 * size_len)) - 1 else value
    return int.from_bytes(buf[pos:pos + id_len], "big"), length, data


def _elements(buf: bytes) -> Iterator[tuple[int, bytes]]:
    """(id, payload) of the complete elements of known size in a payload read into memory."""
    pos = 0
    while True:
        try:
            found = _parse_header(buf, pos)
        except ValueError:
            return
        if found is None or found[1] is None or found[2] + found[1] > len(buf):
            return
        yield found[0], buf[found[2]:found[2] + found[1]]
        pos = found[2] + found[1]


def _children(buf: bytes) -> dict[int, bytes]:
    """The first payload of each element id among the elements of `buf`."""
    out: dict[int, bytes] = {}
    for eid, payload in _elements(buf):
        out.setdefault(eid, payload)
    return out


def count_frames(path: str | Path) -> VideoFrames:
    """The frames of a Matroska file, counted from its element headers alone (no frame is read),
    and why the count may stop short: an empty file, no Matroska header, a last frame cut short,
    bytes that are no element."""
    try:
        with MatroskaVideo(path) as video:
            return video.count()
    except ValueError as exc:
        return VideoFrames(0, str(exc))
    except OSError as exc:
        return VideoFrames(0, f"cannot be read ({exc.strerror or exc})")
