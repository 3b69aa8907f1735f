"""Multi-view consistency: carve an occupancy volume from the views' masks, project it back.

A voxel is kept when (almost) every calibrated view that looks at it sees foreground there: one
view's miss is forgiven (a hole in that view), so the volume survives a single view's false
negatives, and a false positive of one view finds no support in the others and disappears from
the volume. Projected back, the volume drops each view's unsupported blobs and fills its holes.
The carving is coarse-to-fine (8, 4, 2, 1 cm, then 5 mm inside the kept cells: each level halves a
cell per axis), with vectorized projections: thousands of points per level. Starting at 2 cm, the
first level alone projected the whole cube's 125,000 cells; splitting cells in 4 per axis (8 cm, 2
cm, 5 mm) gave the last level 64 points for each cell of 2 cm the hand touches, 25,000 for a
forearm and hand, where halving gives it 15,000.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import cv2
import numpy as np

from manus_core.cameras import CameraRig
from manus_core.errors import SegmentationError
from manus_core.jit import jit

from .background import bounding_window, fill_holes, grow_window, window_box

# The distance to a view's mask is computed in a window this many px around it and bounded
# below by the distance to the mask's box beyond: exact for every voxel whose projected radius is
# below 0.955 times it (a 5 mm voxel half a metre from a 1280x720 camera is about 10 px, 17 cm
# from it 23 px). Coarser cells, larger, are tested against the bound: it keeps a few more of
# them, whose 5 mm voxels are then tested exactly (48 px gave the same masks on 480 views of a
# full-size take, its distances taking 1.4 times as long).
DISTANCE_PAD = 24
# OpenCV's 3x3 L2 transform steps 0.955 px along an axis and 1.3693 px diagonally, so its distance
# is at least 0.955 times the Euclidean one: the bound beyond the window is scaled by it.
CHAMFER_AXIS = 0.955

# The volume that keeps a view's part the strict one does not: hits in this share of the views that
# see a voxel, and in at least this many views (on a rig of four, no less than the strict volume asks)
MAJORITY = 0.5
MAJORITY_MIN_VIEWS = 3

Window = tuple[slice, slice]


@dataclass(frozen=True)
class Occupancy:
    """Kept voxel centres (N,3) in the world and the voxel edge (m); `pixels`: the centres' pixels
    (C,N,2) in the rig's views when carve has them (they are drawn from, not projected again)."""

    centres: np.ndarray
    voxel: float
    pixels: np.ndarray | None = None


def default_bounds(rig: CameraRig, margin: float = 0.1) -> np.ndarray:
    """The box (2,3) of the cube, shrunk by `margin` of its size: the world's origin is the cube's
    centre (the tag layout fixes it) and the cameras sit on its walls, so the cube reaches as far
    from the origin as the farthest camera, on every axis. (Per axis, the box of the camera
    centres cuts off the table when no camera looks up from below it, and is flat when the
    cameras are: four cameras around the table at one height carved nothing.)"""
    half = np.full(3, np.abs(rig.centers).max() * (1 - margin))
    return np.stack([-half, half])


def pixels(rig: CameraRig, points: np.ndarray) -> np.ndarray:
    """The pixel (C,N,2) int64 each point (N,3) falls on in each view; -1 where it projects to no
    pixel (a point in the camera's plane gives NaN or a value beyond int64)."""
    return np.rint(np.clip(np.nan_to_num(rig.project(points), nan=-1.0), -1.0, 1e9)).astype(np.int64)


@dataclass(frozen=True)
class _Distances:
    """Each view's distance (px) to its mask, for the views with one (`views`, their indices in the
    rig): computed in a window (the mask's box grown by DISTANCE_PAD), and outside it a lower bound,
    CHAMFER_AXIS times the distance to the mask's box. Flat arrays for _distance_kernel: each
    view's window and box as (row start, stop, column start, stop), its window's distances one view
    after another, each from its `offset`."""

    views: np.ndarray      # (V,) int64
    size: np.ndarray       # (V,2) int64: each view's image (width, height)
    window: np.ndarray     # (V,4) int64
    box: np.ndarray        # (V,4) int64
    offset: np.ndarray     # (V,) int64
    inside: np.ndarray     # (sum of the windows' areas,) float32

    @classmethod
    def of(cls, masks: np.ndarray, boxes: list[Window | None]) -> "_Distances":
        """The distances to masks (C,H,W) of the views with a box (each mask's, bounding_window(mask, 0))."""
        views = np.array([c for c, b in enumerate(boxes) if b is not None], np.int64)
        boxes = [boxes[c] for c in views]
        windows = [grow_window(box, DISTANCE_PAD, masks.shape[1:]) for box in boxes]
        inside = [cv2.distanceTransform((~masks[c][w]).astype(np.uint8), cv2.DIST_L2, 3).ravel()
                  for c, w in zip(views, windows)]
        sizes = np.array([d.size for d in inside], np.int64)
        return cls(views, np.array([masks[c].shape[::-1] for c in views], np.int64).reshape(-1, 2),
                   np.array([_bounds(w) for w in windows], np.int64).reshape(-1, 4),
                   np.array([_bounds(b) for b in boxes], np.int64).reshape(-1, 4),
                   np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64),
                   np.concatenate(inside + [np.zeros(0, np.float32)]))

    def at(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """(V,N) float32: each view's distance to its mask at the pixels uv (C,N,2) (rounded) of
        points at `depth` (C,N) in the rig's views; inf where a point is not seen (behind the
        camera, outside the image or NaN)."""
        return _distance_kernel(uv, depth, self.views, self.size, self.window, self.box, self.offset, self.inside)


def _bounds(window: Window) -> tuple[int, int, int, int]:
    return window[0].start, window[0].stop, window[1].start, window[1].stop


@jit
def _distance_kernel(uv: np.ndarray, depth: np.ndarray, views: np.ndarray, size: np.ndarray, window: np.ndarray,
                     box: np.ndarray, offset: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """_Distances.at, one pass over the points a view: numpy's masks, gathers and bounds made it
    two thirds of carving's time."""
    out = np.full((len(views), uv.shape[1]), np.inf, np.float32)
    axis = np.float32(CHAMFER_AXIS)
    for v in range(len(views)):
        c = views[v]
        r0, r1, c0, c1 = window[v, 0], window[v, 1], window[v, 2], window[v, 3]
        b0, b1, b2, b3 = box[v, 0], box[v, 1], box[v, 2], box[v, 3]
        for i in range(uv.shape[1]):
            fx, fy = np.rint(uv[c, i, 0]), np.rint(uv[c, i, 1])
            if not (depth[c, i] > 1e-3 and fx >= 0 and fy >= 0 and fx < size[v, 0] and fy < size[v, 1]):
                continue
            x, y = int(fx), int(fy)
            if r0 <= y < r1 and c0 <= x < c1:
                out[v, i] = inside[offset[v] + (y - r0) * (c1 - c0) + (x - c0)]
            else:
                dy = max(b0 - y, y - (b1 - 1), 0)
                dx = max(b2 - x, x - (b3 - 1), 0)
                out[v, i] = np.sqrt(np.float32(dx * dx + dy * dy)) * axis
    return out


def _votes(rig: CameraRig, dist: _Distances, points: np.ndarray,
           half: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(seen, hit) counts per point over the views in `dist` (seen when it projects into the image
    in front of the camera, hit when a mask pixel lies within the voxel's projected radius), and
    the points' pixels (C,N,2)."""
    depth = rig.R[:, 2] @ points.T + rig.t[:, 2, None]
    uv = rig.project(points)
    distance = dist.at(uv, depth)
    seen = np.isfinite(distance)
    with np.errstate(divide="ignore"):
        radius = rig.K[dist.views, 0, 0, None] * half * np.sqrt(3) / depth[dist.views] + 1.0
    return seen.sum(axis=0), (seen & (distance <= radius)).sum(axis=0), uv


def carve(rig: CameraRig, masks: np.ndarray, bounds: np.ndarray | None = None, voxel: float = 0.005,
          coarse: float = 0.08, misses: int = 1, miss_fraction: float = 0.2, min_views: int = 2,
          boxes: list[Window | None] | None = None) -> Occupancy:
    """Occupancy of the foreground seen in masks (C,H,W) bool of the rig's views.

    Views with an empty mask say nothing (the hand may be hidden from them behind the table) and
    are left out. Cells are halved from `coarse` until they are `voxel` or smaller (Occupancy.voxel
    says which). A voxel is kept when it is a hit in all but `misses` (or `miss_fraction` of
    them, when more) of the views that see it, and in at least `min_views`: a view can miss
    because something static hides the hand from it (the table from the floor's cameras, which
    see foreground elsewhere), and a big rig has several such views. `boxes`: each mask's box
    (bounding_window(mask, 0)), when the caller has them (each is a pass over a whole view)."""
    masks = np.asarray(masks, bool)
    if masks.shape[0] != len(rig.ids):
        raise SegmentationError(f"carve: {masks.shape[0]} masks for {len(rig.ids)} cameras")
    boxes = [bounding_window(m, 0) for m in masks] if boxes is None else boxes
    use = np.array([b is not None for b in boxes])
    if np.count_nonzero(use) < min_views:
        raise SegmentationError(f"carve: foreground in {np.count_nonzero(use)} views, need {min_views}")
    dist = _Distances.of(masks, boxes)
    bounds = default_bounds(rig) if bounds is None else np.asarray(bounds, float)
    axes = [np.arange(lo + coarse / 2, hi, coarse) for lo, hi in bounds.T]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    # a cell's 8 halves, as offsets from its centre in units of the half's size
    halves = np.stack(np.meshgrid(*[(-0.5, 0.5)] * 3, indexing="ij"), -1).reshape(-1, 3)
    size = coarse
    while True:
        seen, hit, uv = _votes(rig, dist, points, size / 2)
        allowed = np.maximum(misses, np.floor(miss_fraction * seen)).astype(np.int32)
        kept = hit >= np.maximum(seen - allowed, min_views)
        points = points[kept]
        if size <= voxel * 1.001 or not len(points):
            return Occupancy(points, size, uv[:, kept])
        size /= 2
        points = (points[:, None, :] + halves[None] * size).reshape(-1, 3)


def _boxes(rig: CameraRig, occupancy: Occupancy) -> tuple[np.ndarray, np.ndarray]:
    """Each voxel's projection as a box: its centre's pixel (C,N,2) and the half extents (C,N,2)
    of its corners' projections, from the pinhole's derivative at the centre (the lens distortion
    changes a 5 mm voxel's few pixels by a few percent, and is left out of the extents)."""
    centres = occupancy.centres
    uv = rig.project(centres) if occupancy.pixels is None else occupancy.pixels
    return uv, _extents(rig.to_camera(centres), rig.R, rig.K, occupancy.voxel / 2)


@jit
def _extents(cam: np.ndarray, R: np.ndarray, K: np.ndarray, half: float) -> np.ndarray:
    """_boxes' half extents (C,N,2) of voxels at camera coordinates cam (C,N,3): d(x, y)/dX =
    (R0 - x R2, R1 - y R2) / z, whose absolute values summed over X's three axes give the box of a
    cube's corners; NaN in the plane of the camera (its centre's pixel is NaN there too). (In numpy,
    a dozen whole-array passes: two thirds of drawing a volume's boxes.)"""
    out = np.empty((cam.shape[0], cam.shape[1], 2))
    for c in range(cam.shape[0]):
        for i in range(cam.shape[1]):
            z = cam[c, i, 2]
            if z == 0:
                out[c, i, 0] = out[c, i, 1] = np.nan
                continue
            inv = 1.0 / z
            x, y = cam[c, i, 0] * inv, cam[c, i, 1] * inv
            dx = dy = 0.0
            for j in range(3):
                dx += abs(R[c, 0, j] - x * R[c, 2, j])
                dy += abs(R[c, 1, j] - y * R[c, 2, j])
            scale = inv * half
            out[c, i, 0] = (K[c, 0, 0] * dx + abs(K[c, 0, 1]) * dy) * scale
            out[c, i, 1] = K[c, 1, 1] * dy * scale
    return out


def _draw_boxes(uv: np.ndarray, extent: np.ndarray, window: Window) -> np.ndarray:
    """The pixels of `window` whose centres lie in any of the boxes (centres uv (N,2), half extents
    (N,2)): each box's corners marked in a difference image, then summed along both axes."""
    rows, cols = window
    h, w = rows.stop - rows.start, cols.stop - cols.start
    diff = _box_corners(uv, extent, rows.start, cols.start, h, w)
    return cv2.integral(diff, sdepth=cv2.CV_32F)[1:h + 1, 1:w + 1] > 0.5


@jit
def _box_corners(uv: np.ndarray, extent: np.ndarray, top: int, left: int, h: int, w: int) -> np.ndarray:
    """(h+1,w+1) float32: +1 at each box's first row and column in the window and at one past its
    last row and column, -1 at the other two corners; a box behind the camera (NaN) or outside the
    window marks nothing."""
    diff = np.zeros((h + 1, w + 1), np.float32)
    for i in range(uv.shape[0]):
        x0 = np.ceil(uv[i, 0] - extent[i, 0] - left)
        x1 = np.floor(uv[i, 0] + extent[i, 0] - left) + 1
        y0 = np.ceil(uv[i, 1] - extent[i, 1] - top)
        y1 = np.floor(uv[i, 1] + extent[i, 1] - top) + 1
        if np.isnan(x0) or np.isnan(x1) or np.isnan(y0) or np.isnan(y1):
            continue
        a, b = int(min(max(x0, 0.0), w)), int(min(max(x1, 0.0), w))
        c, d = int(min(max(y0, 0.0), h)), int(min(max(y1, 0.0), h))
        if a < b and c < d:
            diff[c, a] += 1
            diff[c, b] -= 1
            diff[d, a] -= 1
            diff[d, b] += 1
    return diff


def project_occupancy(rig: CameraRig, occupancy: Occupancy, shape: tuple[int, int],
                      windows: list[Window | None] | None = None) -> np.ndarray:
    """Silhouettes (C,H,W) bool of the voxels, each drawn as the box of its corners' projections;
    with `windows`, only inside each view's window (None: nothing in that view). (Drawing each
    voxel's centre, faces, edges and corners as points and closing the gaps projected eight times
    the points, and took a 1280x720 view 9 ms.)"""
    h, w = shape
    windows = [(slice(0, h), slice(0, w))] * len(rig.ids) if windows is None else windows
    out = np.zeros((len(rig.ids), h, w), bool)
    for c, drawn in enumerate(_silhouettes(rig, occupancy, windows)):
        if drawn is not None:
            out[c][windows[c]] = drawn
    return out


def _silhouettes(rig: CameraRig, occupancy: Occupancy, windows: list[Window | None]) -> list[np.ndarray | None]:
    """project_occupancy's silhouette in each view's window alone (window-sized; None for a view
    without a window): a frame group's (C,H,W) of mostly empty pixels cost more to allocate
    than drawing the boxes."""
    if not len(occupancy.centres):
        return [None if w is None else np.zeros((w[0].stop - w[0].start, w[1].stop - w[1].start), bool)
                for w in windows]
    uv, extent = _boxes(rig, occupancy)
    return [None if w is None else _draw_boxes(uv[c], extent[c], w) for c, w in enumerate(windows)]


def _supported(parts: np.ndarray, count: int, proj: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Which of a view's `count` labelled parts (0: background) lie within the kernel of `proj`."""
    return _touching(parts, cv2.dilate(proj.view(np.uint8), kernel), count)


@jit
def _touching(parts: np.ndarray, near: np.ndarray, count: int) -> np.ndarray:
    """(count,) bool: the labels of `parts` (0: none) at a pixel where `near` is nonzero. (A boolean
    mask, a gather and a bincount in numpy: a twelfth of consistent_masks' time.)"""
    out = np.zeros(count, np.bool_)
    h, w = parts.shape
    for y in range(h):
        for x in range(w):
            if near[y, x] and parts[y, x] > 0:
                out[parts[y, x]] = True
    return out


def consistent_masks(rig: CameraRig, masks: np.ndarray, support_px: int = 2, boxes: list[Window | None] | None = None,
                     **carve_options) -> tuple[np.ndarray, dict]:
    """Masks (C,H,W) made consistent across the views, and a report.

    Each view keeps every connected part of its own (pixel-accurate) foreground that the carved
    volume supports somewhere (within `support_px`), drops the parts it supports nowhere, and gets
    its holes filled where the volume covers them. All of it happens inside the mask's box: what
    is kept lies in the mask, and a hole is enclosed by it. A part the volume does not hold is
    still kept when a volume carved by a majority (MAJORITY of the views that see a voxel, at least
    MAJORITY_MIN_VIEWS) holds it: something static hides it from more views than the carving
    forgives. `boxes`: as carve's. The report's `boxes` are the consistent masks' boxes (rows,
    columns; None where a view's mask is empty)."""
    masks = np.asarray(masks, bool)
    boxes = [bounding_window(m, 0) for m in masks] if boxes is None else boxes
    occupancy = carve(rig, masks, boxes=boxes, **carve_options)
    if not len(occupancy.centres):
        warnings.warn("multi-view consistency: the views' masks share no volume; masks left as they are",
                      stacklevel=2)
        return masks.copy(), {"voxels": 0, "majority_voxels": 0, "dropped_px": [0] * len(masks),
                              "filled_px": [0] * len(masks), "boxes": boxes}
    # a mask pixel's support depends on the projection up to support_px + 4 px away (the dilation,
    # then the closing's dilation and erosion), and one pixel of background all round
    windows = [None if b is None else grow_window(b, support_px + 5, masks.shape[1:]) for b in boxes]
    projected = _silhouettes(rig, occupancy, windows)
    kernel = np.ones((2 * support_px + 1,) * 2, np.uint8)
    # whole parts, not pixels: a voxel needs hits in nearly every view that sees it, and what
    # something static hides from several views is carved away though the others see it (the
    # forearm below a raised hand, behind the table from the floor's and the low cameras: 11-21 %
    # of a hand take's foreground pixels were dropped, the wrist and forearm in the side views, and
    # MANUS-Hand learnt from masks that cut the arm off in some views only)
    parts, supported = [], []
    for mask, proj, window in zip(masks, projected, windows):
        if window is None:
            parts.append(None)
            supported.append(None)
            continue
        count, labels = cv2.connectedComponents(mask[window].astype(np.uint8), connectivity=8)
        parts.append(labels)
        supported.append(_supported(labels, count, proj, kernel))
    unsupported = [s is not None and not s[1:].all() for s in supported]
    majority_voxels = 0
    # (a view's window is None where its mask is empty)
    if any(unsupported) and sum(w is not None for w in windows) >= MAJORITY_MIN_VIEWS:
        # a part apart from the hand that something static hides from several views (the object on
        # the table, from the floor's cameras and, behind the hand, from above: 14 % of the views of
        # make demo's grasp take lost it) is seen by most of the others
        majority = carve(rig, masks, boxes=boxes,
                         **{**carve_options, "miss_fraction": MAJORITY, "min_views": MAJORITY_MIN_VIEWS})
        majority_voxels = len(majority.centres)
        if majority_voxels:
            more = _silhouettes(rig, majority, [w if u else None for w, u in zip(windows, unsupported)])
            for c in np.flatnonzero(unsupported):
                supported[c] |= _supported(parts[c], len(supported[c]), more[c], kernel)
    # a view's mask is empty outside its window: only the windows are written (np.zeros, whose
    # pages the system hands out zeroed when first touched: zeros_like writes every byte)
    out = np.zeros(masks.shape, bool)
    dropped, filled, kept_boxes = [], [], []
    for c, (mask, proj, window) in enumerate(zip(masks, projected, windows)):
        if window is None:
            dropped.append(0)   # a view that saw nothing (occluded) is not filled from the others
            filled.append(0)
            kept_boxes.append(None)
            continue
        mask = mask[window]
        # (every part supported, as in most views: the mask itself, without a pass over the labels)
        kept = mask if supported[c][1:].all() else supported[c][parts[c]]
        done = kept | (fill_holes(kept) & proj)
        out[c][window] = done
        dropped.append(int(np.count_nonzero(mask & ~kept)))
        filled.append(int(np.count_nonzero(done & ~kept)))
        kept_boxes.append(window_box(done, window))
    return out, {"voxels": int(len(occupancy.centres)), "voxel_m": occupancy.voxel,
                 "majority_voxels": int(majority_voxels), "dropped_px": dropped, "filled_px": filled,
                 "boxes": kept_boxes}
