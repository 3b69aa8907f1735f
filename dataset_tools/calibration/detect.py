"""Detection of calibration targets: AprilTags, ChArUco boards, AprilTag grids and chessboards.

Every detector returns a `Detection`: integer point ids (board point ids, or tag_id * 4 + corner
for tags) with their pixels, so intrinsics, PnP and bundle adjustment treat all targets alike.

Choices measured on the project's test data (docs/calibration.md has the numbers):
- AprilTags: cv2.aruco with CORNER_REFINE_APRILTAG finds the quads; its quad fit reproduces the
  AprilTag library's corners to 0.16 px on upstream's test images. Those corners follow the AprilTag
  library's pixel convention and sit 0.4-0.6 px off in OpenCV's (pixel centres on integers; 0.61 px
  median error on simulated views with exact corners), so for calibration each corner is then
  re-fitted from the tag's four outer edges (tag_edges: 0.04 px median on the same views).
  Small tags (10-20 px) often fail to decode at native resolution, so a second pass decodes on a
  2x upsampled image; the corners of a tag found there still come from the native-resolution quad
  (the upsampled quad fit is 0.4-1.4 px off).
- Chessboards: findChessboardCornersSB finds the board, then cornerSubPix refines each corner with
  a window of 0.3 x its distance to the nearest neighbour corner. A fixed 11x11 window (OpenCV's
  sample) reaches past the squares of strongly foreshortened views and moves corners by ~1 px.
"""

from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator, Sequence

import numpy as np

from .boards import Board, CalibrationError, get_dictionary
from manus_core.errors import DetectionError

_SUBPIX_CRITERIA = (3, 50, 1e-3)  # cv2.TERM_CRITERIA_EPS | COUNT, 50 iterations, 1e-3 px
_SUBPIX_FRACTION = 0.3            # half-window as a fraction of the local corner spacing
VIDEO_SUFFIXES = {".mkv", ".mp4", ".avi", ".mov", ".webm"}
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".pgm", ".ppm"}


@dataclass(frozen=True)
class Detection:
    """What one image shows of a target.

    ids (N,) int64 point ids; xy (N,2) float64 pixels; info: per-detection quality
    (boards: points found, fraction of the board, corner spacing in pixels; tags: per tag its
    shortest side in pixels and the scale of the pass that decoded it; corners always come from
    the native-resolution quad fit).
    """

    ids: np.ndarray
    xy: np.ndarray
    info: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.ids)

    @staticmethod
    def empty() -> "Detection":
        return Detection(np.zeros(0, np.int64), np.zeros((0, 2)), {})


def to_gray(image: np.ndarray) -> np.ndarray:
    """8-bit grey image from grey, BGR or BGRA input."""
    import cv2

    image = np.asarray(image)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if image.dtype != np.uint8:
        raise DetectionError(f"images must be 8-bit, got {image.dtype}")
    return image


class TagDetector:
    """AprilTag (or any cv2.aruco dictionary) detector with native-resolution corners.

    refine: "edges" (default) re-fits every corner from the tag's outer edges, in OpenCV's pixel
    convention (K and dist, when known, let the edges be fitted where they are straight);
    "apriltag" keeps the AprilTag quad fit, identical to the AprilTag library's output.
    max_bit_fraction is OpenCV's errorCorrectionRate: the share of the dictionary's correction
    capacity used (1.0 = 5 bit errors for 36h11). Unknown ids are dropped by the caller (the tag
    layout), so recall matters more than a rare false decode.
    """

    def __init__(self, dictionary: str = "DICT_APRILTAG_36h11", upsample: int = 2,
                 max_bit_fraction: float = 1.0, inverted: bool = False, refine: str = "edges",
                 K: np.ndarray | None = None, dist: np.ndarray | None = None) -> None:
        if refine not in ("edges", "apriltag"):
            raise ValueError(f"refine must be 'edges' or 'apriltag', got {refine!r}")
        self.dictionary_name = dictionary
        self.upsample = int(upsample)
        self.max_bit_fraction = float(max_bit_fraction)
        self.inverted = inverted
        self.refine = refine
        self.K = None if K is None else np.asarray(K, np.float64)
        self.dist = None if dist is None else np.asarray(dist, np.float64).ravel()
        self._cv = None

    def __getstate__(self) -> dict:
        # OpenCV detectors do not pickle; worker processes build their own
        return {**self.__dict__, "_cv": None}

    @property
    def _detector(self):
        import cv2

        if self._cv is None:
            params = cv2.aruco.DetectorParameters()
            params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_APRILTAG
            params.errorCorrectionRate = self.max_bit_fraction
            self._cv = cv2.aruco.ArucoDetector(get_dictionary(self.dictionary_name), params)
        return self._cv

    def detect_tags(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[dict]]:
        """(tag ids (T,), corners (T,4,2) in OpenCV order, per-tag quality dicts).

        Quality: side_px (shortest side), decoded_at (1, or the upsampling of the pass that
        decoded it), fitted (per corner: re-fitted from the edges; always true with "apriltag").
        """
        import cv2

        gray = to_gray(image)
        if self.inverted:
            gray = 255 - gray
        corners, ids, rejected = self._detector.detectMarkers(gray)
        quads = [c.reshape(4, 2).astype(np.float64) for c in corners]
        tag_ids = [] if ids is None else [int(i) for i in ids.ravel()]
        scales = [1] * len(quads)
        if self.upsample > 1:
            # Native quads that failed to decode are candidates for the upsampled pass.
            pool = np.array([c.reshape(4, 2) for c in rejected], np.float64) if len(rejected) else np.zeros((0, 4, 2))
            big = cv2.resize(gray, None, fx=self.upsample, fy=self.upsample, interpolation=cv2.INTER_CUBIC)
            up_corners, up_ids, _ = self._detector.detectMarkers(big)
            have = np.array([q.mean(0) for q in quads]) if quads else np.zeros((0, 2))
            for c, i in zip(up_corners, [] if up_ids is None else up_ids.ravel()):
                q = (c.reshape(4, 2).astype(np.float64) + 0.5) / self.upsample - 0.5
                side = np.linalg.norm(q - np.roll(q, 1, axis=0), axis=1).min()
                if len(have) and np.linalg.norm(have - q.mean(0), axis=1).min() < 0.3 * side:
                    continue
                native, err = _closest_quad(pool, q)
                if native is None or err > 0.3 * side:
                    continue
                quads.append(native)
                tag_ids.append(int(i))
                scales.append(self.upsample)
                have = np.vstack([have, q.mean(0)])
        quads_arr = np.array(quads).reshape(-1, 4, 2)
        refined = np.ones(quads_arr.shape[:2], bool)
        if self.refine == "edges" and len(quads_arr):
            from .tag_edges import refine_tag_corners

            fitted = refine_tag_corners(gray, quads_arr, self.K, self.dist)
            # corners whose edges could not be fitted (cut by the image border, occluded) come
            # back unchanged, i.e. in the AprilTag convention: flagged, and left out of `detect`
            refined = np.any(fitted != quads_arr, axis=2)
            quads_arr = fitted
        sides = np.linalg.norm(quads_arr - np.roll(quads_arr, 1, axis=1), axis=2).min(axis=1) if len(quads) else []
        info = [{"side_px": round(float(s), 2), "decoded_at": k, "fitted": r.tolist()}
                for s, k, r in zip(sides, scales, refined)]
        return np.asarray(tag_ids, np.int64), quads_arr, info

    def detect(self, image: np.ndarray) -> Detection:
        """Tag corners as points: id = tag_id * 4 + corner."""
        ids, quads, info = self.detect_tags(image)
        if len(ids) == 0:
            return Detection.empty()
        # The same id twice (a reflection, a duplicate print) cannot be told apart: drop both.
        uniq, counts = np.unique(ids, return_counts=True)
        keep = np.isin(ids, uniq[counts == 1])
        good = keep[:, None] & np.array([q["fitted"] for q in info], bool)
        pid = (ids[:, None] * 4 + np.arange(4))[good]
        tags = {int(i): q for i, q, k in zip(ids, info, keep) if k}
        return Detection(pid, quads[good], {"tags": tags, "duplicates": int((~keep).sum())})


def _closest_quad(pool: np.ndarray, quad: np.ndarray) -> tuple[np.ndarray | None, float]:
    """The pool quad nearest to `quad`, cyclically re-ordered to match it, and its corner error."""
    if len(pool) == 0:
        return None, np.inf
    j = int(np.argmin(np.linalg.norm(pool.mean(1) - quad.mean(0), axis=1)))
    shifted = np.stack([np.roll(pool[j], s, axis=0) for s in range(4)])
    errs = np.linalg.norm(shifted - quad[None], axis=2).max(axis=1)
    s = int(np.argmin(errs))
    return shifted[s], float(errs[s])


def refine_grid_corners(gray: np.ndarray, xy: np.ndarray, cols: int, rows: int) -> np.ndarray:
    """cornerSubPix on a full (rows*cols,2) chessboard grid with a window per corner spacing."""
    grid = xy.reshape(rows, cols, 2)
    spacing = np.full((rows, cols), np.inf)
    dx = np.linalg.norm(np.diff(grid, axis=1), axis=2)
    dy = np.linalg.norm(np.diff(grid, axis=0), axis=2)
    spacing[:, :-1] = np.minimum(spacing[:, :-1], dx)
    spacing[:, 1:] = np.minimum(spacing[:, 1:], dx)
    spacing[:-1] = np.minimum(spacing[:-1], dy)
    spacing[1:] = np.minimum(spacing[1:], dy)
    return refine_corners(gray, xy, spacing.ravel())


def refine_corners(gray: np.ndarray, xy: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """cornerSubPix with half-window 0.3 x spacing per corner (grouped by window size)."""
    import cv2

    half = np.clip((_SUBPIX_FRACTION * spacing).astype(int), 2, 15)
    out = np.asarray(xy, np.float32).reshape(-1, 2).copy()
    for w in np.unique(half):
        sel = half == w
        out[sel] = cv2.cornerSubPix(gray, out[sel].reshape(-1, 1, 2).copy(), (int(w), int(w)), (-1, -1),
                                    _SUBPIX_CRITERIA).reshape(-1, 2)
    return out.astype(np.float64)


class BoardDetector:
    """Finds one board (chessboard, ChArUco or AprilTag grid) in images."""

    def __init__(self, board: Board, inverted: bool | None = None, upsample: int = 2, quick: bool = False) -> None:
        """quick: only whether the board is there (chessboards: no exhaustive search, no refinement)."""
        import cv2

        self.quick = quick
        self.board = board
        self.inverted = board.inverted if inverted is None else inverted
        self._charuco = None
        self._tags = None
        if board.type == "charuco":
            self._charuco = cv2.aruco.CharucoDetector(board.opencv_board())
        elif board.type == "apriltag-grid":
            self._tags = TagDetector(board.dictionary, upsample=upsample)

    def detect(self, image: np.ndarray) -> Detection:
        import cv2

        gray = to_gray(image)
        if self.inverted:
            gray = 255 - gray
        board = self.board
        total = board.n_points
        if board.type == "chessboard":
            flags = cv2.CALIB_CB_NORMALIZE_IMAGE
            if not self.quick:
                flags |= cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
            ok, corners = cv2.findChessboardCornersSB(gray, (board.cols, board.rows), flags=flags)
            if not ok:
                return Detection.empty()
            xy = corners.reshape(-1, 2).astype(np.float64)
            if not self.quick:
                xy = refine_grid_corners(gray, xy, board.cols, board.rows)
            ids = np.arange(total)
        elif board.type == "charuco":
            corners, cids, _, _ = self._charuco.detectBoard(gray)
            if cids is None or len(cids) < 4:
                return Detection.empty()
            ids = cids.ravel().astype(np.int64)
            xy = corners.reshape(-1, 2).astype(np.float64)
        else:
            found = self._tags.detect(gray)
            keep = found.ids < total
            ids, xy = found.ids[keep], found.xy[keep]
            if len(ids) < 4:
                return Detection.empty()
        return Detection(ids, xy, {"points": int(len(ids)), "fraction": round(len(ids) / total, 3),
                                   "spacing_px": round(_median_spacing(board, ids, xy), 2)})


def _median_spacing(board: Board, ids: np.ndarray, xy: np.ndarray) -> float:
    """Median image distance of neighbouring board points: how large the board appears."""
    pairs = board.neighbour_pairs()
    lookup = np.full(board.n_points, -1)
    lookup[ids] = np.arange(len(ids))
    a, b = lookup[pairs[:, 0]], lookup[pairs[:, 1]]
    ok = (a >= 0) & (b >= 0)
    if not ok.any():
        return float("nan")
    return float(np.median(np.linalg.norm(xy[a[ok]] - xy[b[ok]], axis=1)))


# --- frames from files ------------------------------------------------------------------------

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
            from manus_core.take import Take

            return Take(self.paths[0]).frame_count(self.camera)
        if self.is_video:
            return video_frame_count(self.paths[0])
        return len(self.arrays) if self.arrays is not None else len(self.paths)


def video_frame_count(path: str | os.PathLike) -> int:
    """Number of frames in a video (counted by decoding when the container does not say)."""
    import cv2

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
    import cv2

    if source.camera is not None:
        # a take: JPEG packets are skipped undecoded, only the wanted frames are decoded
        from manus_core.take import Take

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


# --- many cameras in parallel -----------------------------------------------------------------

Target = Board | TagDetector


def _detector_for(target: Target) -> Callable[[np.ndarray], Detection]:
    return target.detect if isinstance(target, TagDetector) else BoardDetector(target).detect


def subsample(source: FrameSource, count: int) -> FrameSource:
    """At most `count` frames of a source, evenly spread (every frame when there are fewer)."""
    n = source.count()
    if n <= count:
        return source
    frames = tuple(int(i) for i in np.unique(np.linspace(0, n - 1, count).round()))
    return FrameSource(source.paths, frames, source.arrays, source.camera)


def detect_source(source: FrameSource, target: Target, on_frame: Callable[[], None] | None = None
                  ) -> tuple[dict[int, Detection], tuple[int, int]]:
    """Detect the target in every frame of one source: ({frame index: Detection}, (width, height)).

    Raises DetectionError when the frames do not all have the same size.
    """
    detect = _detector_for(target)
    found: dict[int, Detection] = {}
    size = None
    for index, gray in read_frames(source):
        shape = (gray.shape[1], gray.shape[0])
        if size is None:
            size = shape
        elif shape != size:
            where = (f"{source.name} frame {index}" if source.is_video or source.camera is not None else
                     source.paths[index] if source.paths else f"image {index}")
            raise DetectionError(f"{where}: image size {shape[0]}x{shape[1]} differs from "
                                 f"{size[0]}x{size[1]} of the first image; one camera, one size")
        det = detect(gray)
        if len(det):
            found[index] = det
        if on_frame is not None:
            on_frame()
    if size is None:
        raise DetectionError(f"{source.name}: no frames could be read")
    return found, size


def _detect_job(args):
    import cv2

    name, source, target, threads = args
    if threads is not None:
        cv2.setNumThreads(threads)  # one process per camera already fills the cores
    try:
        return name, detect_source(source, target), None
    except DetectionError as exc:
        return name, None, str(exc)


def detect_cameras(sources: dict[str, FrameSource], target: Target | dict[str, Target], workers: int | None = None,
                   progress: Callable[[str], None] | None = None
                   ) -> tuple[dict[str, dict[int, Detection]], dict[str, tuple[int, int]]]:
    """Detect a target (or one per camera) in every camera's frames, one process per camera.

    Returns ({camera: {frame index: Detection}}, {camera: (width, height)}). Raises
    DetectionError naming every camera whose frames could not be read or differ in size.
    """
    workers = min(len(sources), workers or os.cpu_count() or 1)
    targets = target if isinstance(target, dict) else {name: target for name in sources}
    jobs = [(name, src, targets[name], None if workers <= 1 else 1) for name, src in sources.items()]
    results: dict[str, dict[int, Detection]] = {}
    sizes: dict[str, tuple[int, int]] = {}
    errors: list[str] = []
    if workers <= 1:
        outputs = map(_detect_job, jobs)
        executor = None
    else:
        import multiprocessing

        # spawn, not fork: a child forked after OpenCV's video decoder or thread pool ran in the
        # parent can deadlock on a lock held at fork time (seen here). Scripts that call this need
        # the usual `if __name__ == "__main__":` guard.
        executor = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))
        outputs = executor.map(_detect_job, jobs)
    try:
        for name, out, err in outputs:
            if err:
                errors.append(f"camera {name}: {err}")
            else:
                results[name], sizes[name] = out
            if progress:
                progress(name)
    finally:
        if executor is not None:
            executor.shutdown()
    if errors:
        raise DetectionError("; ".join(errors))
    return {n: results[n] for n in sources}, {n: sizes[n] for n in sources}


def detect_images(images: Sequence[np.ndarray], target: Target) -> dict[int, Detection]:
    """Detect a target in in-memory images: {image index: Detection} (images without it left out)."""
    return detect_source(FrameSource(arrays=tuple(images)), target)[0]


def diagnose_board(images: Sequence[np.ndarray], board: Board) -> str:
    """Why `board` is found in none of `images`: the usual mistakes tried one by one.

    Returns one sentence naming the parameter of board.toml that is likely wrong (the most common
    complaint about anipose and FreeMoCap is a board silently matching nothing).
    """
    import cv2
    from dataclasses import replace

    grays = [to_gray(i) for i in images]
    n = len(grays)
    b = board
    c, r = b.cols, b.rows
    low = 2 if b.type != "charuco" else 3
    shapes = [(c, r), (r, c), (c - 1, r - 1), (r - 1, c - 1), (c + 1, r + 1), (r + 1, c + 1)]
    best, best_points = None, 0
    # the print's polarity last: ties go to the variant that keeps it
    for inverted in (b.inverted, not b.inverted):
        for cols, rows in dict.fromkeys(s for s in shapes if min(s) >= low):
            variant = replace(b, cols=cols, rows=rows, inverted=inverted)
            if variant == b:
                continue
            det = BoardDetector(variant, quick=True)
            points = sum(len(d) for d in map(det.detect, grays) if _planar_fit(d, variant))
            if points > best_points:
                best, best_points = variant, points
    if best is not None:
        changes = [f"{k} = {str(getattr(best, k)).lower() if k == 'inverted' else getattr(best, k)}"
                   for k in ("cols", "rows", "inverted") if getattr(best, k) != getattr(b, k)]
        hint = ""
        if (best.cols, best.rows) != (c, r) and {best.cols, best.rows} != {c, r}:
            hint = (" (a chessboard's cols and rows count inner corners)" if b.type == "chessboard" else
                    " (a charuco board's cols and rows count squares)" if b.type == "charuco" else "")
        elif (best.cols, best.rows) == (r, c):
            hint = " (cols and rows swapped)"
        return (f"{b.source}: the board is found in none of {n} images as described, but with "
                f"{', '.join(changes)}{hint} it is ({best_points} points)")
    if b.type == "chessboard":
        return (f"{b.source}: no {b.cols}x{b.rows} chessboard in {n} images, nor with the usual mistakes "
                f"(swapped, squares instead of inner corners, inverted): is the board in view, sharp and evenly lit?")
    counts = {}
    for name in (b.dictionary, *_COMMON_DICTIONARIES):
        det = cv2.aruco.ArucoDetector(get_dictionary(name))
        for inv in (False, True):
            counts[(name, inv)] = sum(len(det.detectMarkers(255 - g if inv else g)[0]) for g in grays)
    # ties: the larger dictionary (DICT_4X4_1000 holds every marker of DICT_4X4_50)
    (best, inv), found = max(counts.items(), key=lambda kv: (kv[1], len(get_dictionary(kv[0][0]).bytesList)))
    if found == 0:
        return f"{b.source}: no marker of any common dictionary in {n} images: is the board in view, sharp and evenly lit?"
    if best != b.dictionary:
        return (f"{b.source}: {found} markers of {best} but {counts[(b.dictionary, b.inverted)]} of {b.dictionary} "
                f"were found: set dictionary = \"{best}\"" + (f" and inverted = {str(inv).lower()}" if inv != b.inverted else ""))
    return (f"{b.source}: markers of {b.dictionary} are found ({found}) but never the board: check cols, rows, "
            f"square and marker (boards made by OpenCV before 4.6 with an even number of rows use the old "
            f"'legacy' layout)")


# Dictionaries people print boards from, tried when a board matches nothing.
_COMMON_DICTIONARIES = ("DICT_4X4_50", "DICT_4X4_1000", "DICT_5X5_100", "DICT_5X5_1000", "DICT_6X6_250",
                        "DICT_6X6_1000", "DICT_7X7_1000", "DICT_ARUCO_ORIGINAL", "DICT_APRILTAG_36h11")


def _planar_fit(det: Detection, board: Board, tol_px: float = 3.0) -> bool:
    """True when the detected points fit one homography of the board plane (a real board, not
    corners interpolated from markers of a board with another layout)."""
    import cv2

    if len(det) < 6:
        return False
    obj = board.object_points()[det.ids, :2]
    H, _ = cv2.findHomography(obj, det.xy, 0)
    if H is None:
        return False
    proj = cv2.perspectiveTransform(obj.reshape(-1, 1, 2), H).reshape(-1, 2)
    return bool(np.median(np.linalg.norm(proj - det.xy, axis=1)) < tol_px)
