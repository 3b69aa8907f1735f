"""One camera's stream in a take: a reader thread, a ring, a writer thread.

A reader only pulls frames from its camera and never waits on the disk: a full ring costs a
frame (counted as an overflow, visible as a sequence gap) rather than stalling the camera's own
buffers. The one exception is a simulated camera on a fast virtual clock: it has no real time to
keep, so its reader waits for the writer; otherwise a loaded machine would lose frames that a
real camera at that rate would not. A writer muxes the JPEG bytes as they came (raw frames from
machine-vision cameras are JPEG-encoded first) and appends the frame's row to frames.csv only
after its packet is written, so that rows and packets agree.

The ring is a plain deque: a reader's append and a writer's popleft are atomic under the GIL,
so handing a frame over costs no lock and wakes no thread. The writer looks at its ring every
PASS_S and stores what queued up in one system call. Woken for every frame instead (a
queue.Queue), 75 cameras' readers and writers made 4 context switches and 57 us of CPU per frame
before any byte was written, and one system call per frame (docs/recording.md, "Speed"). One writer per camera
rather than a few shared ones: a write that the kernel holds up (writeback, the journal) then
holds up that camera only.
"""

from __future__ import annotations

import contextlib
import errno
import os
import threading
import time
from collections import deque
from pathlib import Path
from typing import Protocol

from manus_core.errors import CameraDisconnected
from manus_core.frames_csv import HEADER, format_row

from ..cameras import Camera, Frame
from ..clock import Clock, is_fast
from ..mkv import MkvWriter
from .jpeg import frame_jpeg
from .report import CameraReport
from .stop import StopFlag

READ_TIMEOUT_S = 0.2          # how often a reader looks at the stop flag
STALL_S = 2.0                 # a camera that hands out nothing for this long has stopped
FIRST_FRAME_S = 5.0           # ... except before its first frame (streams take time to start)
WRITE_BATCH = 32              # frames a writer that fell behind stores in one system call
PASS_S = 0.02                 # a writer looks at its ring this often: 2 to 3 frames per call at 120 FPS
FULL_WAIT_S = 0.001           # a lossless reader (fast virtual clock) waits this long for room in its ring


class StreamOwner(Protocol):
    """What a stream needs of the take it belongs to (the Recorder)."""

    path: Path
    clock: Clock
    stop: StopFlag
    end_ns: int
    csv: FrameCsv | None
    jpeg_params: list[int]

    def event(self, cam: str, what: str, message: str) -> None: ...


class FrameCsv:
    """frames.csv, shared by the writers: whole rows only, even when the disk fills up."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._lock = threading.Lock()
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o644)
        self._size = 0
        self.append((HEADER + "\n").encode())

    def append(self, row: bytes) -> None:
        with self._lock:
            done = 0
            try:
                while done < len(row):
                    n = os.write(self._fd, row[done:])
                    if n == 0:
                        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self.path))
                    done += n
            except OSError as exc:
                os.ftruncate(self._fd, self._size)
                os.lseek(self._fd, self._size, os.SEEK_SET)
                raise OSError(exc.errno, exc.strerror, str(self.path)) from exc
            self._size += done

    def close(self) -> None:
        with self._lock:
            if self._fd is not None:
                with contextlib.suppress(OSError):
                    os.fsync(self._fd)
                os.close(self._fd)
                self._fd = None


_END = object()   # a reader's last item: its writer finishes the file


class Stream:
    """One camera: its reader thread, ring buffer, writer thread and report."""

    def __init__(self, rec: StreamOwner, cam_id: str, camera: Camera, report: CameraReport, ring: int) -> None:
        self.rec, self.id, self.camera, self.report = rec, cam_id, camera, report
        self.ring: deque = deque()
        self.capacity = ring
        self.lossless = is_fast(rec.clock)
        self.mkv: MkvWriter | None = None
        self.write_failed = False
        self.abandoned = False
        # (JPEG bytes, CLOCK_MONOTONIC ns) of the latest stored frame, for a monitor: one
        # assignment of bytes the writer has anyway, never a copy or a decode
        self.latest: tuple[bytes, int] | None = None
        self.reader = threading.Thread(target=self._read_loop, name=f"read-{cam_id}", daemon=True)
        self.writer = threading.Thread(target=self._write_loop, name=f"write-{cam_id}", daemon=True)

    @property
    def active(self) -> bool:
        return self.report.status == "ok" and self.reader.is_alive()

    @property
    def fill(self) -> float:
        """How full the ring is, 0 to 1."""
        return min(1.0, len(self.ring) / self.capacity)

    def lost(self, status: str, message: str) -> None:
        self.report.status, self.report.error = status, message
        self.report.t_lost_ns = self.rec.clock.now_ns()
        self.rec.event(self.id, status, message)

    def _read_loop(self) -> None:
        rec, cam = self.rec, self.camera
        last_frame = time.monotonic()
        got_any = False
        try:
            while not rec.stop.is_set():
                try:
                    frame = cam.read(READ_TIMEOUT_S)
                except CameraDisconnected as exc:
                    self.lost("disconnected", str(exc))
                    break
                except Exception as exc:   # any backend failure takes out this camera only
                    self.lost("failed", f"{type(exc).__name__}: {exc}")
                    break
                if frame is None:
                    if rec.clock.now_ns() >= rec.end_ns:
                        break
                    idle = time.monotonic() - last_frame
                    if idle > (STALL_S if got_any else FIRST_FRAME_S):
                        self.lost("stopped", f"no frame for {idle:.1f} s")
                        break
                    continue
                got_any = True
                last_frame = time.monotonic()
                self._put(frame)
                # the first frame that arrives at or after the end is kept: every frame read is stored
                if frame.t_host_ns >= rec.end_ns:
                    break
        finally:
            self.ring.append(_END)

    def _put(self, frame: Frame) -> None:
        ring = self.ring
        if len(ring) < self.capacity:
            ring.append(frame)
            return
        if self.lossless:
            while self.writer.is_alive():
                time.sleep(FULL_WAIT_S)
                if len(ring) < self.capacity:
                    ring.append(frame)
                    return
        self.report.overflows += 1

    def _write_loop(self) -> None:
        ring, report = self.ring, self.report
        try:
            ended = False
            while not ended:
                started = time.monotonic()
                # whatever queued up since the last look goes out in one write: a writer that fell
                # behind catches up with fewer system calls per frame
                batch: list[Frame] = []
                while ring and len(batch) < WRITE_BATCH:
                    item = ring.popleft()
                    if item is _END:
                        ended = True
                        break
                    batch.append(item)
                if batch and not self.write_failed:
                    self._store_or_fail(batch)
                elif batch:
                    report.unwritten += len(batch)
                if not ring and self.abandoned:   # its reader never came back: what it delivered is stored
                    break
                rest = PASS_S - (time.monotonic() - started)
                if not ended and rest > 0 and len(ring) < WRITE_BATCH:
                    time.sleep(rest)
        finally:
            if self.mkv is not None:
                try:
                    self.mkv.close()
                except OSError as exc:
                    self.rec.event(self.id, "finish-failed", str(exc))

    def _store_or_fail(self, batch: list[Frame]) -> None:
        try:
            self._store(batch)
            return
        except Exception as exc:
            error, left = exc, batch
        if len(batch) > 1:
            # the batch failed as a whole: store its frames one by one as far as they go
            for i, frame in enumerate(batch):
                try:
                    self._store([frame])
                except Exception as exc:
                    error, left = exc, batch[i:]
                    break
            else:
                return
        self.write_failed = True
        self.report.unwritten += len(left)
        self.rec.stop.set(self._failure(error))

    def _failure(self, exc: Exception) -> str:
        name = Path(getattr(exc, "filename", None) or self.mkv.path)
        with contextlib.suppress(ValueError):
            name = name.relative_to(self.rec.path)
        if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
            return f"disk full (ENOSPC) while writing {name}"
        return f"writer of camera {self.id} failed: {type(exc).__name__}: {exc}"

    def _store(self, frames: list[Frame]) -> None:
        """Packets first, then their frames.csv rows; rows that cannot be written take their
        packets back out, so that rows and packets always agree."""
        report = self.report
        datas, rows = [], []
        for frame in frames:
            data, flags = frame_jpeg(frame, self.rec.jpeg_params)
            datas.append(data)
            rows.append(format_row(self.id, frame.seq, frame.t_device_ns, frame.t_host_ns, len(data), flags))
        self.mkv.write(datas)
        try:
            self.rec.csv.append("".join(rows).encode())
        except OSError:
            self.mkv.rollback()
            raise
        for frame, data in zip(frames, datas):
            if report.last_seq is not None and frame.seq > report.last_seq + 1:
                report.seq_gaps += frame.seq - report.last_seq - 1
            if report.first_seq is None:
                report.first_seq = frame.seq
            report.last_seq = frame.seq if report.last_seq is None else max(report.last_seq, frame.seq)
            report.bytes += len(data)
            report.encoding = frame.encoding
        report.frames += len(frames)
        self.latest = (datas[-1], time.monotonic_ns())
