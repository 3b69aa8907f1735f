"""Intrinsics of one camera (OpenCV model, k1 k2 p1 p2 k3) from views of a board.

Views are chosen to cover the image (a video of a waved board holds hundreds of near-duplicate
frames), calibrated with cv2.calibrateCamera, and views whose error is far above the others
(a motion-blurred or mis-detected board) are dropped once before the final fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from manus_core.errors import IntrinsicsError

from .boards import Board
from .detect import Detection

MIN_POINTS_PER_VIEW = 6
MIN_VIEWS = 4


@dataclass(frozen=True)
class Intrinsics:
    """K (3,3), dist (5,), size (width, height), rms_px, and what it was computed from."""

    K: np.ndarray
    dist: np.ndarray
    size: tuple[int, int]
    rms_px: float
    views: tuple[int, ...]            # frame indices used
    view_rms_px: np.ndarray           # (V,) per used view
    rejected: tuple[int, ...]         # frame indices dropped as outliers
    points: int
    coverage: float                   # share of a 10x10 image grid touched by board points
    rvecs: np.ndarray                 # (V,3) board poses of the used views
    tvecs: np.ndarray                 # (V,3)

    def summary(self) -> dict:
        return {"fx": float(self.K[0, 0]), "fy": float(self.K[1, 1]), "cx": float(self.K[0, 2]),
                "cy": float(self.K[1, 2]), "dist": self.dist.tolist(), "rms_px": round(self.rms_px, 4),
                "views": len(self.views), "rejected_views": list(self.rejected), "points": self.points,
                "coverage": round(self.coverage, 3)}


def coverage(xy: np.ndarray, size: tuple[int, int], cells: int = 10) -> float:
    """Share of a cells x cells grid over the image that holds at least one point."""
    if len(xy) == 0:
        return 0.0
    w, h = size
    ij = np.clip((np.asarray(xy) / [w, h] * cells).astype(int), 0, cells - 1)
    return len(np.unique(ij[:, 1] * cells + ij[:, 0])) / cells**2


def select_views(detections: dict[int, Detection], size: tuple[int, int], max_views: int) -> list[int]:
    """Up to max_views frames that together cover the image and the board's poses.

    Greedy: each step takes the view that adds the most new cells of a 10x10 image grid, ties
    broken by the number of points; once the grid is covered, the remaining views are spread
    evenly in time (different board tilts).
    """
    frames = [f for f, d in detections.items() if len(d) >= MIN_POINTS_PER_VIEW]
    if len(frames) <= max_views:
        return sorted(frames)
    w, h = size
    cells = {}
    for f in frames:
        xy = detections[f].xy
        ij = np.clip((xy / [w, h] * 10).astype(int), 0, 9)
        cells[f] = set((ij[:, 1] * 10 + ij[:, 0]).tolist())
    chosen: list[int] = []
    covered: set[int] = set()
    remaining = set(frames)
    while remaining and len(chosen) < max_views // 2:
        best = max(remaining, key=lambda f: (len(cells[f] - covered), len(detections[f])))
        if not cells[best] - covered:
            break
        chosen.append(best)
        covered |= cells[best]
        remaining.discard(best)
    rest = sorted(remaining)
    take = max_views - len(chosen)
    if take > 0 and rest:
        chosen += [rest[i] for i in np.unique(np.linspace(0, len(rest) - 1, take).round().astype(int))]
    return sorted(chosen)


def _object_points(board: Board, det: Detection) -> tuple[np.ndarray, np.ndarray]:
    obj = board.object_points()[det.ids].astype(np.float32)
    return obj.reshape(-1, 1, 3), det.xy.astype(np.float32).reshape(-1, 1, 2)


def calibrate_intrinsics(detections: dict[int, Detection], board: Board, size: tuple[int, int],
                         camera: str = "camera", max_views: int = 60, fix_k3: bool = False,
                         outlier_factor: float = 3.0) -> Intrinsics:
    """Calibrate one camera from its board detections ({frame index: Detection}).

    Raises IntrinsicsError naming `camera` when there are too few usable views.
    """
    usable = {f: d for f, d in detections.items() if len(d) >= MIN_POINTS_PER_VIEW}
    if len(usable) < MIN_VIEWS:
        raise IntrinsicsError(
            camera, f"the board is found in {len(usable)} frame(s) with >= {MIN_POINTS_PER_VIEW} "
            f"points (of {len(detections)} with any); at least {MIN_VIEWS} are needed: show the board "
            f"closer, tilted, and in more positions")
    frames = select_views(usable, size, max_views)
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    rejected: list[int] = []
    for attempt in range(2):
        obj, img = zip(*(_object_points(board, usable[f]) for f in frames))
        rms, K, dist, rvecs, tvecs, _, _, view_err = cv2.calibrateCameraExtended(
            list(obj), list(img), size, None, None, flags=flags)
        view_err = view_err.ravel()
        limit = max(outlier_factor * np.median(view_err), 1.0)
        bad = view_err > limit
        if attempt == 1 or not bad.any() or len(frames) - bad.sum() < MIN_VIEWS:
            break
        rejected += [f for f, b in zip(frames, bad) if b]
        frames = [f for f, b in zip(frames, bad) if not b]
    xy = np.concatenate([usable[f].xy for f in frames])
    return Intrinsics(K, dist.ravel()[:5], tuple(size), float(rms), tuple(frames), view_err,
                      tuple(rejected), len(xy), coverage(xy, size),
                      np.array(rvecs).reshape(-1, 3), np.array(tvecs).reshape(-1, 3))

