"""An append-only Matroska muxer for MJPEG packets that stays readable at every moment.

The recorder stores each camera's JPEG bytes as they came (no decoding, no re-encoding), one
SimpleBlock per frame, with the frame index as presentation time: the track's timestamp scale
is one frame period, so block k has timestamp k (DESIGN.md, "On disk").

Why a muxer of its own rather than an ffmpeg subprocess per camera: no pipe copy and no JPEG
boundary parsing per byte (53 cameras at 120 FPS are ~1 GB/s), the packet count always equals
the frames handed in, and a failed write can be rolled back to a frame boundary.

Crash safety: the Segment and the open Cluster are written with the "unknown size" marker that
Matroska allows for exactly these two elements (live streams use it), and every block goes to
the kernel in one writev() call without user-space buffering. A process that is killed leaves
a file that ffmpeg and OpenCV read up to the last complete block. close() then makes the file
tidy: it sets the cluster and segment sizes, writes Cues (random access by frame index) and a
SeekHead into space reserved at the start, and the duration into the Info element.

Reading back is manus_core.matroska's: frame counts from the element headers, and packets from
any frame on through these Cues.
"""

from __future__ import annotations

import errno
import os
import struct
from collections.abc import Sequence
from pathlib import Path

from manus_core.matroska import (
    CLUSTER, CUE_CLUSTER_POSITION, CUE_POINT, CUE_TIME, CUE_TRACK, CUE_TRACK_POSITIONS, CUES, DURATION, EBML, INFO,
    MUXING_APP, SEEK, SEEK_HEAD, SEEK_ID, SEEK_POSITION, SEGMENT, SIMPLE_BLOCK, TIMESTAMP, TIMESTAMP_SCALE, TRACK_ENTRY,
    TRACKS, VOID, WRITING_APP,
)

UNKNOWN_SIZE = b"\x01\xff\xff\xff\xff\xff\xff\xff"  # 8-byte vint with every value bit set
SEEK_HEAD_SPACE = 96      # reserved for a SeekHead of three entries (68 bytes) plus a Void
DURATION_SPACE = 11       # a float64 Duration element: id (2) + size (1) + 8
MAX_BLOCK_DELTA = 32767   # a block's timestamp is a signed 16-bit offset from its cluster's
MAX_BATCH = 256           # frames per write(): up to 3 iovecs each, under the kernel's IOV_MAX of 1024


def vint(value: int, length: int | None = None) -> bytes:
    """An EBML variable-length unsigned integer (element sizes); `length` forces the width."""
    if length is None:
        length = 1
        while value >= (1 << (7 * length)) - 1:
            length += 1
    if length > 8 or value >= (1 << (7 * length)) - 1:
        raise ValueError(f"{value} does not fit an EBML size of {length} bytes")
    return (value | (1 << (7 * length))).to_bytes(length, "big")


def element_id(eid: int) -> bytes:
    return eid.to_bytes((eid.bit_length() + 7) // 8, "big")


def element(eid: int, payload: bytes) -> bytes:
    return element_id(eid) + vint(len(payload)) + payload


def uint(eid: int, value: int) -> bytes:
    return element(eid, value.to_bytes(max(1, (value.bit_length() + 7) // 8), "big"))


def fixed_uint(eid: int, value: int) -> bytes:
    """An unsigned integer of 8 bytes, so that it can be patched in place later."""
    return element(eid, value.to_bytes(8, "big"))


def text(eid: int, value: str) -> bytes:
    return element(eid, value.encode("utf-8"))


def void(total: int) -> bytes:
    """A Void element of exactly `total` bytes (at least 2)."""
    if total < 2:
        raise ValueError("a Void element takes at least 2 bytes")
    # one size byte covers payloads up to 126; beyond that an 8-byte size keeps the arithmetic simple
    if total - 2 <= 126:
        return bytes([VOID]) + vint(total - 2, 1) + bytes(total - 2)
    return bytes([VOID]) + vint(total - 9, 8) + bytes(total - 9)


class MkvWriter:
    """One camera's MJPEG track in a Matroska file; frames are appended with write().

    fps sets the timestamp scale (one tick per frame); cluster_frames bounds a cluster (a
    cluster is also the unit of Cues, so it is the granularity of seeking).
    """

    def __init__(self, path: str | Path, width: int, height: int, fps: float, *, name: str = "",
                 cluster_frames: int | None = None, fsync: bool = True) -> None:
        if fps <= 0 or width <= 0 or height <= 0:
            raise ValueError(f"{path}: width, height and fps must be positive")
        self.path = Path(path)
        self.fps = float(fps)
        self.timestamp_scale_ns = max(1, int(round(1e9 / fps)))
        self.cluster_frames = int(min(cluster_frames or max(1, round(fps)), MAX_BLOCK_DELTA))
        self.fsync = fsync
        self.frames = 0
        self._fd: int | None = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o644)
        self._cues: list[tuple[int, int]] = []     # (cluster timestamp, cluster offset in the segment)
        self._cluster: int | None = None           # file offset of the open cluster
        self._cluster_ts = 0
        self._last: tuple[int, int | None, int, int] | None = None  # state before the last write()
        self._last_count = 0
        try:
            self._write_header(width, height, name)
        except BaseException:
            os.close(self._fd)
            self._fd = None
            raise

    # -- writing ----------------------------------------------------------------------------
    def _write_header(self, width: int, height: int, name: str) -> None:
        head = element(EBML, b"".join([
            uint(0x4286, 1), uint(0x42F7, 1), uint(0x42F2, 4), uint(0x42F3, 8),
            text(0x4282, "matroska"), uint(0x4287, 4), uint(0x4285, 2)]))
        self._segment = len(head) + len(element_id(SEGMENT)) + len(UNKNOWN_SIZE)  # segment data start
        info_payload = b"".join([
            uint(TIMESTAMP_SCALE, self.timestamp_scale_ns), text(MUXING_APP, "manus-capture"),
            text(WRITING_APP, "manus-capture rig.mkv")])
        info = element(INFO, info_payload + void(DURATION_SPACE))
        video = element(0xE0, uint(0xB0, width) + uint(0xBA, height))
        track = element(TRACK_ENTRY, b"".join([
            uint(0xD7, 1), uint(0x73C5, 1), uint(0x83, 1), uint(0x9C, 0), text(0x86, "V_MJPEG"),
            uint(0x23E383, self.timestamp_scale_ns), text(0x536E, name or self.path.stem), video]))
        tracks = element(TRACKS, track)
        self._info_at = self._segment + SEEK_HEAD_SPACE
        self._duration_at = self._info_at + len(info) - DURATION_SPACE
        self._tracks_at = self._info_at + len(info)
        data = head + element_id(SEGMENT) + UNKNOWN_SIZE + void(SEEK_HEAD_SPACE) + info + tracks
        self._write_all([data])
        self._end = len(data)

    def _write_all(self, parts: list[bytes]) -> None:
        """Write every part or raise; a short write (a full disk) is cut back by the caller."""
        total = sum(len(p) for p in parts)
        done = 0
        while done < total:
            if done == 0:
                n = os.writev(self._fd, parts)
            else:
                rest = b"".join(parts)[done:]
                n = os.write(self._fd, rest)
            if n == 0:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self.path))
            done += n

    def write(self, jpegs: bytes | Sequence[bytes]) -> None:
        """Append one frame, or several in one system call. On failure (full disk, I/O error)
        the file is cut back to where it was before this call and the error is raised, so every
        frame written before stays readable."""
        if self._fd is None:
            raise ValueError(f"{self.path}: write() after close()")
        if isinstance(jpegs, (bytes, bytearray, memoryview)):
            jpegs = [jpegs]
        if len(jpegs) > MAX_BATCH:
            raise ValueError(f"{self.path}: at most {MAX_BATCH} frames per write()")
        state = (self._end, self._cluster, self._cluster_ts, len(self._cues))
        pos, k, cluster, cluster_ts = self._end, self.frames, self._cluster, self._cluster_ts
        parts: list[bytes] = []
        closed: list[tuple[int, int]] = []   # (cluster offset, its end): sizes set once written
        for jpeg in jpegs:
            if cluster is None or k - cluster_ts >= self.cluster_frames:
                if cluster is not None:
                    closed.append((cluster, pos))
                cluster, cluster_ts = pos, k
                self._cues.append((k, pos - self._segment))
                head = element_id(CLUSTER) + UNKNOWN_SIZE + uint(TIMESTAMP, k)
                parts.append(head)
                pos += len(head)
            # track 1, timestamp relative to the cluster, keyframe
            block = (bytes([SIMPLE_BLOCK]) + vint(len(jpeg) + 4) + b"\x81"
                     + struct.pack(">hB", k - cluster_ts, 0x80))
            parts += (block, jpeg)
            pos += len(block) + len(jpeg)
            k += 1
        self._last = state
        self._last_count = len(jpegs)
        try:
            self._write_all(parts)
        except OSError as exc:
            self._undo()
            raise OSError(exc.errno, exc.strerror, str(self.path)) from exc
        # an unknown-size cluster is valid up to the next cluster, so a crash before this is harmless
        for offset, end in closed:
            self._set_cluster_size(offset, end)
        self._end, self._cluster, self._cluster_ts, self.frames = pos, cluster, cluster_ts, k

    def rollback(self) -> None:
        """Remove the frames of the last write() (their frames.csv rows could not be written)."""
        if self._last is None:
            raise ValueError(f"{self.path}: nothing to roll back")
        self.frames -= self._last_count
        self._undo()

    def _undo(self) -> None:
        end, cluster, cluster_ts, n_cues = self._last
        self._last = None
        os.ftruncate(self._fd, end)
        os.lseek(self._fd, end, os.SEEK_SET)
        if cluster is not None and cluster != self._cluster:
            # the cut frames opened a cluster, so the previous one was closed: open it again
            os.pwrite(self._fd, UNKNOWN_SIZE, cluster + len(element_id(CLUSTER)))
        self._end, self._cluster, self._cluster_ts = end, cluster, cluster_ts
        del self._cues[n_cues:]

    def _set_cluster_size(self, offset: int, end: int) -> None:
        size_at = offset + len(element_id(CLUSTER))
        os.pwrite(self._fd, vint(end - size_at - 8, 8), size_at)

    # -- finishing --------------------------------------------------------------------------
    def close(self) -> None:
        """Finish the file: sizes, Cues, SeekHead, Duration; fsync. Safe to call twice.

        Finishing needs no more than a few bytes per cluster; on a full disk the Cues are left
        out and the file stays valid without them."""
        if self._fd is None:
            return
        fd = self._fd
        try:
            if self._cluster is not None:
                self._set_cluster_size(self._cluster, self._end)
            seeks = [(INFO, self._info_at - self._segment), (TRACKS, self._tracks_at - self._segment)]
            if self._cues:
                cues = element(CUES, b"".join(
                    element(CUE_POINT, uint(CUE_TIME, ts) + element(
                        CUE_TRACK_POSITIONS, uint(CUE_TRACK, 1) + uint(CUE_CLUSTER_POSITION, pos)))
                    for ts, pos in self._cues))
                try:
                    self._write_all([cues])
                except OSError:
                    os.ftruncate(fd, self._end)
                else:
                    seeks.append((CUES, self._end - self._segment))
                    self._end += len(cues)
            seek_head = element(SEEK_HEAD, b"".join(
                element(SEEK, element(SEEK_ID, element_id(eid)) + fixed_uint(SEEK_POSITION, pos))
                for eid, pos in seeks))
            os.pwrite(fd, seek_head + void(SEEK_HEAD_SPACE - len(seek_head)), self._segment)
            duration = struct.pack(">d", float(self.frames))  # in timestamp-scale units: frames
            os.pwrite(fd, element_id(DURATION) + vint(8, 1) + duration, self._duration_at)
            os.pwrite(fd, vint(self._end - self._segment, 8), self._segment - 8)
            if self.fsync:
                os.fsync(fd)
        finally:
            self._fd = None
            os.close(fd)

    def __enter__(self) -> MkvWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
