"""MediaPipe's palm detector (converted to ONNX by `models install mediapipe-hand`): hand rects from images.

The network sees the image letterboxed into 192x192 (RGB in [0, 1]) and scores 2016 anchors (a
24x24 grid with 2 anchors per cell at stride 8, a 12x12 grid with 6 per cell at stride 16); each
anchor regresses a palm box and 7 palm keypoints (0: wrist centre, 2: middle-finger knuckle).
Detections above `min_score` are merged by weighted non-maximum suppression (overlapping boxes are
averaged, weighted by score, rather than dropped), and each palm becomes a hand rect for the
landmark model: turned to the wrist -> knuckle axis, enlarged 2.6x and moved half a palm towards the
fingers, which MediaPipe's hand pipeline uses and its landmark model was trained on.
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
                 threads: int | None = None, min_score: float = 0.5, iou: float = 0.3) -> None:
        path = Path(path) if path is not None else model_path("mediapipe-hand", f"palm_detection_{variant}")
        self.session = Session(path, device=device, threads=threads)
        self.session.expect_input((None, 3, SIZE, SIZE))
        self.min_score = min_score
        self.iou = iou
        self._anchors = anchors()

    def detect(self, images: list[np.ndarray], max_hands: int = 2) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per image (rects (M,5), scores (M,)), best first, at most max_hands each; one network call."""
        boxed = [letterbox(im) for im in images]
        x = np.stack([b[0] for b in boxed])[..., ::-1].transpose(0, 3, 1, 2)
        raw, logits = self.session.run(np.ascontiguousarray(x, dtype=np.float32) * np.float32(1 / 255))
        scores = 1 / (1 + np.exp(-np.clip(logits[..., 0].astype(np.float64), -100, 100)))
        return [self._decode(raw[i], scores[i], scale, offset, max_hands)
                for i, (_, scale, offset) in enumerate(boxed)]

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
