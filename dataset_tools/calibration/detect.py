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

detect_source and detect_cameras run a detector over the frames of frames.FrameSource (one
process per camera); diagnose.py says why a board is found nowhere.
"""


from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from typing import Callable, Sequence

import cv2
import numpy as np

from manus_core.errors import DetectionError
from manus_core.progress import Progress, silent

from .boards import Board, get_dictionary
from .frames import FrameSource, read_frames, to_gray
from .tag_edges import refine_tag_corners

_SUBPIX_CRITERIA = (3, 50, 1e-3)  # cv2.TERM_CRITERIA_EPS | COUNT, 50 iterations, 1e-3 px
_SUBPIX_FRACTION = 0.3            # half-window as a fraction of the local corner spacing


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
        if self._cv is None:
            params = cv2.aruco.DetectorParameters()
            params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_APRILTAG
            params.errorCorrectionRate = self.max_bit_fraction
            self._cv = cv2.aruco.ArucoDetector(get_dictionary(self.dictionary_name), params)
        return self._cv

    def detect_tags(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[dict]]:
        """(tag ids (T,), corners (T,4,2) in OpenCV order, per-tag quality dicts).

        Quality: side_px (shortest side), face_on (the quad's area over half its longer diagonal
        squared: 1 for a tag seen head-on, about the cosine of the viewing angle at a slant),
        decoded_at (1, or the upsampling of the pass that decoded it), fitted (per corner:
        re-fitted from the edges; always true with "apriltag").
        """
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
            fitted = refine_tag_corners(gray, quads_arr, self.K, self.dist)
            # corners whose edges could not be fitted (cut by the image border, occluded) come
            # back unchanged, i.e. in the AprilTag convention: flagged, and left out of `detect`
            refined = np.any(fitted != quads_arr, axis=2)
            quads_arr = fitted
        sides = np.linalg.norm(quads_arr - np.roll(quads_arr, 1, axis=1), axis=2).min(axis=1)
        diag = quads_arr[:, 2:] - quads_arr[:, :2]          # (T,2,2): corner 0 to 2 and 1 to 3
        area = 0.5 * np.abs(diag[:, 0, 0] * diag[:, 1, 1] - diag[:, 0, 1] * diag[:, 1, 0])
        face_on = area / np.maximum(0.5 * (diag ** 2).sum(axis=2).max(axis=1), 1e-9)
        info = [{"side_px": round(float(s), 2), "face_on": round(float(f), 3), "decoded_at": k, "fitted": r.tolist()}
                for s, f, k, r in zip(sides, face_on, scales, refined)]
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


# --- detection over frames, many cameras in parallel ------------------------------------------

Target = Board | TagDetector


def _detector_for(target: Target) -> Callable[[np.ndarray], Detection]:
    return target.detect if isinstance(target, TagDetector) else BoardDetector(target).detect


def _stage(target: Target) -> str:
    """The progress stage that detecting `target` reports."""
    return "tag detection" if isinstance(target, TagDetector) else "board detection"


def detect_source(source: FrameSource, target: Target, progress: Progress = silent
                  ) -> tuple[dict[int, Detection], tuple[int, int]]:
    """Detect the target in every frame of one source: ({frame index: Detection}, (width, height)).

    progress("board detection" or "tag detection", frames done, frames to read) after each
    frame (no total for a whole video: counting its frames would mean decoding it twice).
    Raises DetectionError when the frames do not all have the same size.
    """
    detect = _detector_for(target)
    stage = _stage(target)
    total = len(source.frames) if source.frames is not None else None if source.is_video else source.count()
    progress(stage, 0, total)
    found: dict[int, Detection] = {}
    size = None
    for done, (index, gray) in enumerate(read_frames(source), start=1):
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
        progress(stage, done, total)
    if size is None:
        raise DetectionError(f"{source.name}: no frames could be read")
    return found, size


def _detect_job(args):
    name, source, target, threads = args
    if threads is not None:
        cv2.setNumThreads(threads)  # one process per camera already fills the cores
    try:
        return name, detect_source(source, target), None
    except DetectionError as exc:
        return name, None, str(exc)


def detect_cameras(sources: dict[str, FrameSource], target: Target | dict[str, Target], workers: int | None = None,
                   progress: Progress = silent
                   ) -> tuple[dict[str, dict[int, Detection]], dict[str, tuple[int, int]]]:
    """Detect a target (or one per camera) in every camera's frames, one process per camera.

    progress("board detection" or "tag detection", cameras done, cameras) as each camera ends.
    Returns ({camera: {frame index: Detection}}, {camera: (width, height)}). Raises
    DetectionError naming every camera whose frames could not be read or differ in size.
    """
    workers = min(len(sources), workers or os.cpu_count() or 1)
    targets = target if isinstance(target, dict) else {name: target for name in sources}
    jobs = [(name, src, targets[name], None if workers <= 1 else 1) for name, src in sources.items()]
    stage = _stage(next(iter(targets.values()))) if targets else "detection"
    progress(stage, 0, len(jobs))
    results: dict[str, dict[int, Detection]] = {}
    sizes: dict[str, tuple[int, int]] = {}
    errors: list[str] = []
    if workers <= 1:
        outputs = map(_detect_job, jobs)
        executor = None
    else:
        # spawn, not fork: a child forked after OpenCV's video decoder or thread pool ran in the
        # parent can deadlock on a lock held at fork time (seen here). Scripts that call this need
        # the usual `if __name__ == "__main__":` guard.
        executor = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))
        outputs = executor.map(_detect_job, jobs)
    try:
        for done, (name, out, err) in enumerate(outputs, start=1):
            if err:
                errors.append(f"camera {name}: {err}")
            else:
                results[name], sizes[name] = out
            progress(stage, done, len(jobs))
    finally:
        if executor is not None:
            executor.shutdown()
    if errors:
        raise DetectionError("; ".join(errors))
    return {n: results[n] for n in sources}, {n: sizes[n] for n in sources}


def detect_images(images: Sequence[np.ndarray], target: Target) -> dict[int, Detection]:
    """Detect a target in in-memory images: {image index: Detection} (images without it left out)."""
    return detect_source(FrameSource(arrays=tuple(images)), target)[0]
