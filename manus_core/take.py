"""Read-only access to a recorded take folder (DESIGN.md, "On disk").

    TAKE/take.json      kind, cameras, fps, resolution, sync mode, start/stop, status, LED log
    TAKE/frames.csv     one row per received frame (manus_core.frames_csv reads it)
    TAKE/cams/CAM.mkv   one MJPEG stream per camera, frames in the order of their frames.csv rows
                        (an imported take may name other MJPEG files in take.json's "videos")

A camera's *frame index* k is its k-th row in frames.csv and its k-th packet in CAM.mkv. Frames are
read as raw JPEG packets (no decoding while skipping; a Matroska video is entered at the frame asked
for through its Cues, manus_core.matroska) and decoded only when asked for.
Every error names the file and what is wrong (TakeError, exit code 2 in the CLI).
"""

from __future__ import annotations

import json
import os
import socket
from collections.abc import Iterator, Sequence
from itertools import islice
from pathlib import Path

import cv2
import numpy as np
import simplejpeg

from manus_core import jpeg_window
from manus_core.errors import TakeError
from manus_core.frames_csv import FILE_NAME as FRAMES_CSV
from manus_core.frames_csv import read_frames_csv
from manus_core.matroska import MatroskaVideo, VideoFrames, count_frames

MATROSKA_SUFFIXES = (".mkv", ".mka", ".webm")
SEEK_GAP = 240   # frames: beyond two of the recorder's clusters, entering through the Cues is cheaper
BOOT_ID = Path("/proc/sys/kernel/random/boot_id")


def _start_ticks(pid: int) -> int | None:
    """When process `pid` started (clock ticks since boot, /proc/PID/stat field 22); None if it
    is gone. With the boot id it names one process for good: a pid alone is reused."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return int(stat.rsplit(")", 1)[1].split()[19])


def recorder_identity() -> dict:
    """Who is recording: written into take.json while the take runs, so that a later process can
    tell a take still being recorded from one whose recorder died."""
    boot = BOOT_ID.read_text().strip() if BOOT_ID.is_file() else ""
    return {"pid": os.getpid(), "started": _start_ticks(os.getpid()), "host": socket.gethostname(), "boot_id": boot}


def recorder_alive(meta: dict) -> bool:
    """Whether the process named by take.json's "recorder" may still be writing the take: true
    for a recorder on another host (it cannot be checked from here), false after a reboot."""
    who = meta.get("recorder")
    if not isinstance(who, dict) or not isinstance(who.get("pid"), int):
        return False
    here = recorder_identity()
    if who.get("host") != here["host"]:
        return True
    return who.get("boot_id") == here["boot_id"] and _start_ticks(who["pid"]) == who.get("started")


class Take:
    """A take folder. `cameras` come from take.json (ids, or objects with an "id")."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        meta_path = self.path / "take.json"
        if self.path.is_file():
            raise TakeError(f"{self.path}: a file, not a take folder (give the folder that holds take.json)")
        if not self.path.is_dir():
            raise TakeError(f"{self.path}: no such take folder")
        try:
            self.meta: dict = json.loads(meta_path.read_text())
        except FileNotFoundError:
            raise TakeError(f"{meta_path}: missing (not a take folder)") from None
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise TakeError(f"{meta_path}: not valid JSON ({exc})") from None
        if not isinstance(self.meta, dict):
            raise TakeError(f"{meta_path}: expected a JSON object")
        cams = self.meta.get("cameras")
        if not isinstance(cams, list) or not cams:
            raise TakeError(f"{meta_path}: cameras: expected a non-empty list of camera ids")
        try:
            self.cameras: tuple[str, ...] = tuple(str(c["id"] if isinstance(c, dict) else c) for c in cams)
        except KeyError:
            raise TakeError(f"{meta_path}: cameras: an entry has no 'id'") from None
        self._frames: dict[str, np.ndarray] | None = None
        self._readable: dict[str, int] = {}

    @property
    def recorder_running(self) -> bool:
        """Whether the process that records this take may still be writing it (take.json's
        "recorder"; a take whose status is no longer "recording" is never being written)."""
        return self.meta.get("status") == "recording" and recorder_alive(self.meta)

    @property
    def fps(self) -> float | None:
        fps = self.meta.get("fps")
        return float(fps) if isinstance(fps, (int, float)) else None

    @property
    def frames(self) -> dict[str, np.ndarray]:
        """frames.csv as columns: cam (str), seq, t_device_ns, t_host_ns, bytes (int64), flags."""
        if self._frames is None:
            self._frames = read_frames_csv(self.path / FRAMES_CSV)
        return self._frames

    def camera_frames(self, cam: str) -> dict[str, np.ndarray]:
        """The frames.csv rows of one camera, in order: row k is frame index k."""
        self._check_camera(cam)
        mine = self.frames["cam"] == cam
        return {k: v[mine] for k, v in self.frames.items()}

    def frame_count(self, cam: str) -> int:
        self._check_camera(cam)
        return int(np.count_nonzero(self.frames["cam"] == cam))

    def video_file(self, cam: str) -> Path:
        """Where a camera's video is, whether or not it is there: cams/CAM.mkv, or the file that
        take.json's "videos" names for it (an imported release's video, read where it lies;
        relative to the take folder)."""
        self._check_camera(cam)
        named = self.meta.get("videos", {})
        if isinstance(named, dict) and isinstance(named.get(cam), str):
            return self.path / named[cam]
        return self.path / "cams" / f"{cam}.mkv"

    def video_path(self, cam: str) -> Path:
        path = self.video_file(cam)
        if not path.is_file():
            raise TakeError(f"{path}: missing (camera {cam} of take.json has no video)")
        return path

    def video_frames(self, cam: str) -> VideoFrames:
        """The complete frames of a camera's video and why there may be fewer than were written,
        counted without decoding (a Matroska video from its element headers alone)."""
        path = self.video_file(cam)
        if not path.is_file():
            return VideoFrames(0, "missing")
        if path.suffix in MATROSKA_SUFFIXES:
            return count_frames(path)
        try:
            return VideoFrames(sum(1 for _ in video_packets(path)), None)
        except TakeError as exc:
            return VideoFrames(0, str(exc))

    def readable_frames(self, cam: str) -> int:
        """How many of a camera's frames.csv rows have an image: all of them unless its video was
        cut short (a crash mid-take), whose missing frames every stage treats as not captured."""
        if cam not in self._readable:
            self._readable[cam] = min(self.frame_count(cam), self.video_frames(cam).frames)
        return self._readable[cam]

    def missing_frames(self) -> dict[str, tuple[int, int]]:
        """{camera: (frames with an image, frames.csv rows)} of the cameras whose video is shorter
        than frames.csv says."""
        counts = {cam: (self.readable_frames(cam), self.frame_count(cam)) for cam in self.cameras}
        return {cam: c for cam, c in counts.items() if c[0] < c[1]}

    def missing_notes(self, cameras: Sequence[str] | None = None) -> list[str]:
        """One line per camera (of `cameras`, default all) whose video is cut short: what every
        stage says before it goes on with the frames that exist."""
        missing = self.missing_frames()
        return [f"camera {cam}: {self.video_file(cam).name} holds {have} of its {rows} frames.csv rows (cut short: "
                f"a crash mid-take?): frames {have}-{rows - 1} have no image and are left out"
                for cam, (have, rows) in missing.items() if cameras is None or cam in cameras]

    def packets(self, cam: str, start: int = 0) -> Iterator[np.ndarray]:
        """The JPEG packets of a camera's video from frame index `start` on, in order, undecoded
        (1-D uint8 arrays). A Matroska video is entered through its Cues, near `start`."""
        path = self.video_path(cam)
        if path.suffix not in MATROSKA_SUFFIXES:
            return islice(video_packets(path), start, None)
        return _matroska_packets(path, start)

    def iter_frames(self, cam: str, start: int = 0, stop: int | None = None,
                    step: int = 1) -> Iterator[tuple[int, np.ndarray]]:
        """(k, image (H,W,3) BGR uint8) for frame indices start, start+step, ... < stop.

        Skipped frames are not decoded. A video that ends before `stop` (or before its frames.csv
        rows when stop is None) raises TakeError naming the file and both counts.
        """
        for k, frame in self.iter_encoded(cam, start, stop, step):
            yield k, frame.decode()

    def iter_encoded(self, cam: str, start: int = 0, stop: int | None = None,
                     step: int = 1) -> Iterator[tuple[int, EncodedFrame]]:
        """As iter_frames, undecoded: (k, EncodedFrame), for a reader that decodes each frame
        whole or only the window it needs."""
        expected = self.frame_count(cam) if stop is None else stop
        path = self.video_path(cam)
        k = start - 1
        for k, packet in enumerate(self.packets(cam, start), start):
            if k >= expected:
                return
            if (k - start) % step == 0:
                yield k, EncodedFrame(packet, path, k)
        if k + 1 < expected:
            raise TakeError(f"{path}: has {k + 1} frames, frames.csv (or the request) needs {expected}")

    def read_frame(self, cam: str, k: int) -> np.ndarray:
        """Frame index k of a camera, (H,W,3) BGR uint8."""
        count = self.frame_count(cam)
        if not 0 <= k < count:
            raise TakeError(f"{self.path / FRAMES_CSV}: camera {cam} has no frame {k} ({count} frames)")
        # iter_frames raises TakeError when the video is shorter, so there is always one frame.
        return next(image for _, image in self.iter_frames(cam, k, k + 1))

    def read_frames(self, cam: str, indices) -> dict[int, np.ndarray]:
        """{k: image (H,W,3) BGR uint8} for the frame indices asked for (-1 ignored), in one pass
        over the video: only those are decoded."""
        return dict(self.stream_frames(cam, indices))

    def stream_frames(self, cam: str, indices, out: np.ndarray | None = None) -> Iterator[tuple[int, np.ndarray]]:
        """(k, image) for the distinct frame indices asked for (-1 ignored), in increasing order:
        only those are decoded, and only one is held at a time. The video is read forward and
        entered again through its Cues across a gap of more than SEEK_GAP frames. A video without
        one of them raises TakeError naming the file.

        out: an (H,W,3) uint8 C-contiguous array each frame is decoded into (and yielded as, so it
        holds a frame until the next is asked for), such as a frame group's buffer: no new memory
        and no copy a frame; a frame of another size raises TakeError."""
        wanted = np.unique([int(k) for k in indices if k >= 0])
        path, i = self.video_path(cam), 0
        while i < len(wanted):
            start = int(wanted[i])
            for k, packet in enumerate(self.packets(cam, start), start):
                if k == wanted[i]:
                    yield k, _decode(packet, path, k, out)
                    i += 1
                    if i == len(wanted) or wanted[i] - k > SEEK_GAP:
                        break
            else:
                raise TakeError(f"{path}: has no frame {wanted[i]}")

    def _check_camera(self, cam: str) -> None:
        if cam not in self.cameras:
            raise TakeError(f"{self.path / 'take.json'}: no camera {cam!r} "
                            f"(cameras: {', '.join(self.cameras)})")


def _matroska_packets(path: Path, start: int) -> Iterator[np.ndarray]:
    try:
        video = MatroskaVideo(path)
    except ValueError as exc:
        raise TakeError(f"{path}: {exc}") from None
    with video:
        yield from video.packets(start)


def video_packets(path: Path) -> Iterator[np.ndarray]:
    """The packets of a video file, in order, undecoded (1-D uint8 arrays)."""
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG, [cv2.CAP_PROP_FORMAT, -1])
    if not cap.isOpened():
        raise TakeError(f"{path}: cannot be opened as a video (corrupt, or not MJPEG in Matroska or AVI)")
    try:
        while True:
            ok, packet = cap.read()
            if not ok:
                return
            yield packet.reshape(-1)
    finally:
        cap.release()


class EncodedFrame:
    """Frame k of a video as its JPEG packet, decoded when asked for: whole, or a window of it."""

    __slots__ = ("packet", "path", "k")

    def __init__(self, packet: np.ndarray, path: Path, k: int) -> None:
        self.packet, self.path, self.k = packet, path, k

    def decode(self) -> np.ndarray:
        """The whole frame, (H,W,3) BGR uint8."""
        return _decode(self.packet, self.path, self.k)

    def decode_window(self, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
        """The frame (H,W,3) BGR uint8 with at least its columns x0..x1-1 and rows y0..y1-1
        (clipped to it) decoded, the same pixels as a whole decode's, and the rest undefined: for a
        reader that looks only there. Through jpeg_window where it is built and the frame decodes
        there, else the whole frame."""
        height, width = _size(self.packet)
        if jpeg_window.available() and width:
            x0, y0, x1, y1 = _clip(x0, y0, x1, y1, width, height)
            image = np.empty((height, width, 3), np.uint8)
            try:
                jpeg_window.decode_window(self.packet, x0, y0, x1 - x0, y1 - y0, image)
                return image
            except ValueError:
                pass    # as a whole decode does: OpenCV's reading of what libjpeg refuses
        return self.decode()


def _clip(x0: int, y0: int, x1: int, y1: int, width: int, height: int) -> tuple[int, int, int, int]:
    """A window within a width x height frame; the whole frame where nothing of it is inside."""
    x0, y0, x1, y1 = max(int(x0), 0), max(int(y0), 0), min(int(x1), width), min(int(y1), height)
    return (x0, y0, x1, y1) if x1 > x0 and y1 > y0 else (0, 0, width, height)


def _size(packet: np.ndarray) -> tuple[int, int]:
    """(height, width) from a JPEG's header; (0, 0) where it has none."""
    try:
        return simplejpeg.decode_jpeg_header(packet)[:2]
    except ValueError:
        return 0, 0


def _decode(packet: np.ndarray, path: Path, k: int, out: np.ndarray | None = None) -> np.ndarray:
    # simplejpeg: the same libjpeg-turbo as OpenCV and the same pixels, in about half of imdecode's
    # time for the cube's 1280x720 frames. It refuses a scan that libjpeg decodes with a warning (a
    # bit flipped on the link), and a frame larger than `out`: those go to OpenCV, which decodes
    # them as it always did.
    try:
        image = simplejpeg.decode_jpeg(packet, colorspace="BGR", buffer=out)
    except ValueError:
        image = cv2.imdecode(packet, cv2.IMREAD_COLOR)
        if image is None:
            raise TakeError(f"{path}: frame {k} is not a decodable JPEG ({packet.size} bytes)") from None
        if out is not None and image.shape == out.shape:
            out[...] = image
    if out is None:
        return image
    if image.shape != out.shape:
        raise TakeError(f"{path}: frame {k} is {image.shape[1]}x{image.shape[0]}, "
                        f"the take's frames {out.shape[1]}x{out.shape[0]}")
    return out
