"""MediaPipe's palm detector (converted to ONNX by `models install mediapipe-hand`): hand rects from images.

The network sees the image letterboxed into 192x192 (RGB in [0, 1]) and scores 2016 anchors (a
24x24 grid with 2 anchors per cell at stride 8, a 12x12 grid with 6 per cell at stride 16); each
anchor regresses a palm box and 7 palm keypoints (0: wrist centre, 2: middle-finger knuckle).
Detections above `min_score` are merged by weighted non-maximum suppression (overlapping boxes are
averaged, weighted by score, rather than dropped), and each palm becomes a hand rect for the
landmark model: turned to the wrist -> knuckle axis, enlarged 2.6x and moved half a palm towards the
fingers, which MediaPipe's hand pipeline uses and its landmark model was trained on.

With `tiles`, a wide (or tall) image is also looked at as squares of its shorter side
(`square_tiles`), each filling the network's input: letterboxed, a 16:9 frame leaves 44 % of the
input black and shrinks a hand 1.8x further. On the demo's 320x180 grasp, where a hand's joints
span 30-50 px, the palm detector found it in 39 % of the views that see it whole, in 74 % with
the tiles, at four images' cost instead of one (docs/keypoints.md).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .install import model_path
from .runtime import Session

SIZE = 192
ANCHOR_GRIDS = ((24, 2), (12, 6))      # (cells per side, anchors per cell)
RECT_SCALE = 2.6
RECT_SHIFT = -0.5                      # in palm heights along the crop's y axis (negative: fingers)


def anchors() -> np.ndarray:
    """(2016,2) anchor centres in [0, 1] input coordinates, in the network's output order."""
    out = []
    for cells, per_cell in ANCHOR_GRIDS:
        centre = (np.arange(cells) + 0.5) / cells
        yy, xx = np.meshgrid(centre, centre, indexing="ij")
        out.append(np.repeat(np.stack([xx.ravel(), yy.ravel()], axis=-1), per_cell, axis=0))
    return np.concatenate(out)


def letterbox(image: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Fit an image into SIZE x SIZE keeping its aspect (black bars): tensor, scale, offset.

    Input coordinate u (pixel centres) is image coordinate (u - offset) / scale.
    """
    h, w = image.shape[:2]
    scale = SIZE / max(h, w)
    offset = (np.array([SIZE, SIZE]) - np.array([w, h]) * scale) / 2
    M = np.array([[scale, 0, offset[0] + 0.5 * scale - 0.5], [0, scale, offset[1] + 0.5 * scale - 0.5]])
    boxed = cv2.warpAffine(image, M, (SIZE, SIZE), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    return boxed, scale, M[:, 2]


def square_tiles(width: int, height: int) -> np.ndarray:
    """(N,2) top-left corners (x, y) of squares of the image's shorter side that cover it, evenly
    spread, as few as overlap by at least half a side (so that a hand up to that size lies whole in
    one): two at 4:3, three at 16:9 (overlapping by 0.61); a nearly square image is one tile, the
    whole image letterboxed."""
    short, long = min(width, height), max(width, height)
    n = 1 if long < 1.05 * short else int(np.ceil(2 * long / short - 1 - 1e-9))
    along = np.linspace(0, long - short, n).round().astype(int)
    zeros = np.zeros(n, int)
    return np.stack([along, zeros] if width >= height else [zeros, along], axis=1)


def weighted_nms(boxes: np.ndarray, scores: np.ndarray, extra: np.ndarray, iou: float) -> tuple:
    """Greedy weighted NMS. boxes (M,4) x0,y0,x1,y1; extra (M,D) values averaged like the boxes.

    Each kept detection is the score-weighted mean of the detections overlapping its seed by more
    than `iou`, with the seed's score. Loops over kept detections (a handful), not over anchors.
    """
    order = np.argsort(-scores)
    boxes, scores, extra = boxes[order], scores[order], extra[order]
    area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    alive = np.ones(len(boxes), bool)
    kept_boxes, kept_scores, kept_extra = [], [], []
    while alive.any():
        seed = np.flatnonzero(alive)[0]
        lo = np.maximum(boxes[seed, :2], boxes[:, :2])
        hi = np.minimum(boxes[seed, 2:], boxes[:, 2:])
        inter = np.prod(np.clip(hi - lo, 0, None), axis=1)
        overlap = inter / (area[seed] + area - inter)
        group = alive & (overlap > iou)
        group[seed] = True
        weight = scores[group] / scores[group].sum()
        kept_boxes.append(weight @ boxes[group])
        kept_extra.append(weight @ extra[group])
        kept_scores.append(scores[seed])
        alive &= ~group
    return (np.array(kept_boxes).reshape(-1, 4), np.array(kept_scores),
            np.array(kept_extra).reshape(-1, extra.shape[1]))


class PalmDetector:
    """Hand rects (M,5) [cx, cy, w, h, angle] in image pixels, and scores, from whole images."""

    def __init__(self, variant: str = "full", path: str | Path | None = None, device: str = "auto",
                 threads: int | None = None, min_score: float = 0.5, iou: float = 0.3, tiles: bool = False) -> None:
        path = Path(path) if path is not None else model_path("mediapipe-hand", f"palm_detection_{variant}")
        self.session = Session(path, device=device, threads=threads)
        self.session.expect_input((None, 3, SIZE, SIZE))
        self.min_score = min_score
        self.iou = iou
        self.tiles = tiles
        self._anchors = anchors()

    def detect(self, images: list[np.ndarray], max_hands: int = 2) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per image (rects (M,5), scores (M,)), best first, at most max_hands each; one network call
        over every image, whole and (with `tiles`) in square tiles."""
        # the whole image as well: a hand too large for the tiles' overlap is cut in every tile
        corners = [np.zeros((1, 2), int) if len(xy) == 1 or not self.tiles else np.r_[[[0, 0]], xy]
                   for xy in (square_tiles(im.shape[1], im.shape[0]) for im in images)]
        boxed = [letterbox(im if k == 0 else im[y:y + min(im.shape[:2]), x:x + min(im.shape[:2])])
                 for im, xy in zip(images, corners) for k, (x, y) in enumerate(xy)]
        x = np.stack([b[0] for b in boxed])[..., ::-1].transpose(0, 3, 1, 2)
        raw, logits = self.session.run(np.ascontiguousarray(x, dtype=np.float32) * np.float32(1 / 255))
        scores = 1 / (1 + np.exp(-np.clip(logits[..., 0].astype(np.float64), -100, 100)))
        found = [self._decode(raw[i], scores[i], scale, offset, max_hands)
                 for i, (_, scale, offset) in enumerate(boxed)]
        out, start = [], 0
        for xy in corners:
            views = found[start:start + len(xy)]
            start += len(xy)
            if len(views) == 1:
                out.append(views[0])
                continue
            rects = np.concatenate([r + np.r_[corner, 0, 0, 0] for (r, _), corner in zip(views, xy)])
            out.append(self._merge(rects, np.concatenate([sc for _, sc in views]), max_hands))
        return out

    def _merge(self, rects: np.ndarray, scores: np.ndarray, max_hands: int) -> tuple[np.ndarray, np.ndarray]:
        """One rect per hand found in the whole image and its tiles (the score-weighted mean of a
        hand's rects, its angle through its unit vector)."""
        if len(rects) < 2:
            return rects, scores
        half = rects[:, 2:3] / 2
        boxes = np.concatenate([rects[:, :2] - half, rects[:, :2] + half], axis=1)
        boxes, scores, turn = weighted_nms(boxes, scores, np.column_stack([np.cos(rects[:, 4]), np.sin(rects[:, 4])]),
                                           self.iou)
        side = boxes[:, 2] - boxes[:, 0]
        rects = np.column_stack([(boxes[:, :2] + boxes[:, 2:]) / 2, side, side, np.arctan2(turn[:, 1], turn[:, 0])])
        return rects[:max_hands], scores[:max_hands]

    def _decode(self, raw: np.ndarray, scores: np.ndarray, scale: float, offset: np.ndarray,
                max_hands: int) -> tuple[np.ndarray, np.ndarray]:
        keep = scores >= self.min_score
        if not keep.any():
            return np.zeros((0, 5)), np.zeros(0)
        raw, scores, anchor = raw[keep].astype(np.float64), scores[keep], self._anchors[keep]
        # Offsets and sizes are in input pixels relative to the anchor centre; to input pixels
        # (pixel-centre convention) throughout.
        centre = raw[:, :2] + anchor * SIZE - 0.5
        half = raw[:, 2:4] / 2
        boxes = np.concatenate([centre - half, centre + half], axis=1)
        points = raw[:, 4:18].reshape(-1, 7, 2) + anchor[:, None] * SIZE - 0.5
        boxes, scores, points = weighted_nms(boxes, scores, points.reshape(-1, 14), self.iou)
        boxes, scores, points = boxes[:max_hands], scores[:max_hands], points[:max_hands].reshape(-1, 7, 2)
        # Back to image pixels.
        boxes = (boxes - np.tile(offset, 2)) / scale
        points = (points - offset) / scale
        d = points[:, 2] - points[:, 0]
        angle = np.arctan2(d[:, 0], -d[:, 1])
        w, h = boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]
        centre = (boxes[:, :2] + boxes[:, 2:]) / 2
        up = np.stack([np.sin(angle), -np.cos(angle)], axis=-1)
        centre = centre - RECT_SHIFT * h[:, None] * up
        side = np.maximum(w, h) * RECT_SCALE
        return np.column_stack([centre, side, side, angle]), scores
