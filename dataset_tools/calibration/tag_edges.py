"""Sub-pixel refinement of square-tag corners from their four outer edges.

OpenCV's corner refinements look at a window around each corner; on small or blurred tags that
window reaches into the tag's data cells and pulls the corner inwards. The outer edge of the black
border, though, is a clean step for one cell on either side (black border inside, white quiet zone
outside). We locate that step along many short profiles across each edge, fit a straight line per
edge (after undistortion, where the edge really is straight) and intersect neighbouring lines.
"""

from __future__ import annotations

import cv2
import numpy as np

TAG_CELLS = 8  # AprilTag 36h11 and ArUco 6x6: data plus one black border cell on each side


# OpenCV's undistortion is a fixed-point iteration that contracts by only 0.7-0.8 a step near the
# corners of a strongly barrel-distorted lens (k1 = -0.3): its default 5 steps left edge points
# pixels off there, and bent the fitted lines
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)


def _undistort(points: np.ndarray, K, dist) -> np.ndarray:
    if K is None:
        return points
    flat = points.reshape(-1, 1, 2).astype(np.float64)
    return cv2.undistortPoints(flat, K, dist, P=K, criteria=UNDISTORT_CRITERIA).reshape(points.shape)


def _distort(points: np.ndarray, K, dist) -> np.ndarray:
    if K is None:
        return points
    Kinv = np.linalg.inv(K)
    h = np.concatenate([points.reshape(-1, 2), np.ones((points.size // 2, 1))], axis=1) @ Kinv.T
    out, _ = cv2.projectPoints(h, np.zeros(3), np.zeros(3), K, dist)
    return out.reshape(points.shape)


def refine_tag_corners(gray: np.ndarray, quads: np.ndarray, K: np.ndarray | None = None,
                       dist: np.ndarray | None = None, samples: int = 24, steps: int = 17,
                       cells: int = TAG_CELLS) -> np.ndarray:
    """Refine coarse tag corners (Q,4,2) in a grey image; returns (Q,4,2) float64 pixels.

    K and dist, when given, are used so that edges are fitted where they are straight. Corners
    whose edges show no step (occluded or outside the image) keep their coarse position.
    """
    quads = np.asarray(quads, np.float64).reshape(-1, 4, 2)
    if len(quads) == 0:
        return quads
    img = np.asarray(gray, np.float32)
    a = quads
    b = np.roll(quads, -1, axis=1)                                 # edge i runs corner i -> i+1
    length = np.linalg.norm(b - a, axis=2)                         # (Q,4)
    tangent = (b - a) / np.maximum(length, 1e-9)[..., None]
    normal = np.stack([tangent[..., 1], -tangent[..., 0]], axis=-1)
    centre = quads.mean(axis=1, keepdims=True)
    outward = np.sign(np.einsum("qei,qei->qe", (a + b) / 2 - centre, normal))[..., None]
    normal = normal * np.where(outward == 0, 1, outward)
    # half the profile: most of a cell, so the profile stays on the border and the quiet zone
    half = np.clip(0.8 * length.mean(axis=1) / cells, 1.0, 4.0)[:, None, None, None]  # (Q,1,1,1)
    f = np.linspace(0.15, 0.85, samples)[None, None, :, None]
    o = np.linspace(-1, 1, steps)[None, None, None, :] * half     # (Q,1,1,P)
    base = a[:, :, None, :] + f * (b - a)[:, :, None, :]           # (Q,4,S,2)
    pts = base[:, :, :, None, :] + o[..., None] * normal[:, :, None, None, :]  # (Q,4,S,P,2)
    flat = pts.reshape(-1, 2).astype(np.float32)
    n = len(flat)
    rows = -(-n // 1024)  # cv2.remap maps must stay under 32767 on a side
    mx = np.full(rows * 1024, -10, np.float32)
    my = np.full(rows * 1024, -10, np.float32)
    mx[:n], my[:n] = flat[:, 0], flat[:, 1]
    prof = cv2.remap(img, mx.reshape(rows, 1024), my.reshape(rows, 1024), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=-1).reshape(-1)[:n].reshape(pts.shape[:-1])
    inside = (flat[:, 0] >= 0) & (flat[:, 1] >= 0) & (flat[:, 0] <= img.shape[1] - 1) & (flat[:, 1] <= img.shape[0] - 1)
    inside = inside.reshape(pts.shape[:-1]).all(axis=-1)          # (Q,4,S)
    grad = np.diff(prof, axis=-1)                                  # dark inside -> bright outside
    mid = (o[..., 1:] + o[..., :-1]) / 2
    g = np.maximum(grad, 0)
    contrast = prof[..., -2:].mean(axis=-1) - prof[..., :2].mean(axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        loc = (g * mid).sum(axis=-1) / g.sum(axis=-1)              # (Q,4,S) gradient centroid
    good = inside & (contrast > 20) & np.isfinite(loc)
    edge_pts = base + np.nan_to_num(loc)[..., None] * normal[:, :, None, :]
    edge_pts = _undistort(edge_pts, K, dist)
    w = good.astype(np.float64)
    wsum = w.sum(axis=-1, keepdims=True)                           # (Q,4,1)
    mean = (w[..., None] * edge_pts).sum(axis=2) / np.maximum(wsum, 1)
    d = edge_pts - mean[:, :, None, :]
    cov = np.einsum("qes,qesi,qesj->qeij", w, d, d)
    _, vecs = np.linalg.eigh(cov)
    direction = vecs[..., :, 1]                                    # largest eigenvalue: along the edge
    line_n = np.stack([-direction[..., 1], direction[..., 0]], axis=-1)
    lines = np.concatenate([line_n, -np.einsum("qei,qei->qe", line_n, mean)[..., None]], axis=-1)
    prev = np.roll(lines, 1, axis=1)                               # corner i joins edges i-1 and i
    x = np.cross(prev, lines)
    with np.errstate(invalid="ignore", divide="ignore"):
        corners = x[..., :2] / x[..., 2:3]
    corners = _distort(corners, K, dist)
    enough = (wsum[..., 0] >= samples // 2)
    ok = enough & np.roll(enough, 1, axis=1) & np.isfinite(corners).all(axis=-1)
    ok &= np.linalg.norm(corners - quads, axis=-1) < 0.5 * length.mean(axis=1, keepdims=True) / cells
    # a corner that cannot be fitted (cut off by the image border, hidden) leaves its two edges
    # ending in a guess: the quad of a tag the border cuts is clipped to the image, so its edge
    # there is not the tag's, and a neighbouring corner fitted on it came out 0.4 px off
    ok &= np.roll(ok, 1, axis=1) & np.roll(ok, -1, axis=1)
    return np.where(ok[..., None], corners, quads)
