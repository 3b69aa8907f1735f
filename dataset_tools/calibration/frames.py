"""Where calibration frames come from: image files, one video, a camera of a take, or arrays.

A `FrameSource` describes the frames rather than holding them, so that detection worker processes
read their own; `read_frames` yields them as 8-bit grey images.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

import cv2
import numpy as np

from manus_core.errors import DetectionError, TakeError
from manus_core.take import Take

VIDEO_SUFFIXES = {".mkv", ".mp4", ".avi", ".mov", ".webm"}
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".pgm", ".ppm"}


def to_gray(image: np.ndarray) -> np.ndarray:
    """8-bit grey image from grey, BGR or BGRA input."""
    image = np.asarray(image)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if image.dtype != np.uint8:
        raise DetectionError(f"images must be 8-bit, got {image.dtype}")
    return image



@dataclass(frozen=True)
class FrameSource:
    """Where one camera's frames come from: image files, one video, a camera of a take folder
    (paths = (take folder,), camera = its id), or images in memory.

    frames: the frame indices to read (None: all). Files are described rather than read, so that
    worker processes read the frames themselves.
    """

    paths: tuple[str, ...] = ()
    frames: tuple[int, ...] | None = None
    arrays: tuple[np.ndarray, ...] | None = None
    camera: str | None = None

    @property
    def name(self) -> str:
        if self.camera is not None:
            return f"{self.paths[0]} camera {self.camera}"
        return self.paths[0] if self.paths else "images in memory"

    @property
    def is_video(self) -> bool:
        return (self.arrays is None and self.camera is None and len(self.paths) == 1
                and Path(self.paths[0]).suffix.lower() in VIDEO_SUFFIXES)

    def count(self) -> int:
        """Number of frames the source holds."""
        if self.camera is not None:
            return Take(self.paths[0]).frame_count(self.camera)
        if self.is_video:
            return video_frame_count(self.paths[0])
        return len(self.arrays) if self.arrays is not None else len(self.paths)


def video_frame_count(path: str | os.PathLike) -> int:
    """Number of frames in a video (counted by decoding when the container does not say)."""
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise DetectionError(f"{path}: cannot open video")
    n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    if n <= 0:
        n = 0
        while cap.grab():
            n += 1
    cap.release()
    return n


def read_frames(source: FrameSource) -> Iterator[tuple[int, np.ndarray]]:
    """(frame index, grey image) for every frame of a source, in order."""
    if source.camera is not None:
        # a take: JPEG packets are skipped undecoded, only the wanted frames are decoded
        wanted = None if source.frames is None else set(source.frames)
        last = None if wanted is None else max(wanted, default=-1)
        for index, packet in enumerate(Take(source.paths[0]).packets(source.camera)):
            if last is not None and index > last:
                break
            if wanted is None or index in wanted:
                image = cv2.imdecode(packet, cv2.IMREAD_GRAYSCALE)
                if image is None:
                    raise DetectionError(f"{source.name}: frame {index} is not a decodable JPEG")
                yield index, image
        return
    if source.is_video:
        path = source.paths[0]
        cap = cv2.VideoCapture(path)
        if not cap.isOpened():
            raise DetectionError(f"{path}: cannot open video")
        wanted = None if source.frames is None else set(source.frames)
        last = None if wanted is None else max(wanted, default=-1)
        index = 0
        try:
            while last is None or index <= last:
                if wanted is not None and index not in wanted:
                    if not cap.grab():
                        break
                else:
                    ok, frame = cap.read()
                    if not ok:
                        break
                    yield index, to_gray(frame)
                index += 1
        finally:
            cap.release()
        return
    count = len(source.arrays) if source.arrays is not None else len(source.paths)
    for index in range(count) if source.frames is None else sorted(set(source.frames)):
        if not 0 <= index < count:
            continue
        if source.arrays is not None:
            yield index, to_gray(source.arrays[index])
            continue
        image = cv2.imread(source.paths[index], cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise DetectionError(f"{source.paths[index]}: not a readable image")
        yield index, image


def unreadable(source: FrameSource) -> str | None:
    """Why a source's frames cannot be read (its first frame is read to find out), or None: what
    lets a calibration leave one camera out instead of stopping in the middle of detection."""
    try:
        first = next(read_frames(FrameSource(source.paths, (0,), source.arrays, source.camera)), None)
    except (DetectionError, TakeError) as exc:
        return str(exc)
    return None if first is not None else f"{source.name}: no frame can be read"


def expand_inputs(paths: Iterable[str | os.PathLike]) -> FrameSource:
    """Image files, folders of images, or one video -> FrameSource (sorted, checked)."""
    files: list[str] = []
    for p in map(Path, paths):
        if p.is_dir():
            files += sorted(str(f) for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES | VIDEO_SUFFIXES)
        elif p.exists():
            files.append(str(p))
        else:
            raise DetectionError(f"{p}: no such file")
    if not files:
        raise DetectionError("no images or videos given")
    videos = [f for f in files if Path(f).suffix.lower() in VIDEO_SUFFIXES]
    if videos and len(files) > 1:
        raise DetectionError(f"{videos[0]}: give one video, or image files, not both")
    return FrameSource(tuple(files))



def subsample(source: FrameSource, count: int) -> FrameSource:
    """At most `count` frames of a source, evenly spread (every frame when there are fewer)."""
    n = source.count()
    if n <= count:
        return source
    frames = tuple(int(i) for i in np.unique(np.linspace(0, n - 1, count).round()))
    return FrameSource(source.paths, frames, source.arrays, source.camera)
