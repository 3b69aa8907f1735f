"""Scoring estimated contacts against the green paint, as in the MANUS paper's contact table.

The accumulated contact of a grasp lives on the hand model's Gaussians. Posed like the hand of
the canonical take that followed the grasp (open, palm to the cameras, carrying the paint), it is
rendered into the ground-truth views, thresholded, and compared pixel by pixel with the paint
masks that segment found in those views: IoU and F1 per view, their means over the views, and
the pooled figures over all pixels of all views.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from dataset_tools.undistort import undistort_points
from manus_core.cameras import CameraRig, scale_intrinsics
from manus_core.errors import EvaluateError

from .contacts import PosedModel, render_values, surface_value
from .splat.trainer import world_to_camera

MIN_PAINT_PX = 20       # a view "shows paint" with at least this many paint pixels
DEFAULT_VIEWS = 10      # ground-truth views per sequence, as in the paper
THRESHOLD = 0.5         # rendered contact value that counts as contact
SUPERSAMPLE = 3


@dataclass(frozen=True)
class Scores:
    """Per view `iou`, `f1` (V,) on camera `cameras`; their means; the pooled values over all pixels."""

    cameras: tuple[str, ...]
    iou: np.ndarray
    f1: np.ndarray
    pooled_iou: float
    pooled_f1: float

    @property
    def mean_iou(self) -> float:
        return float(np.mean(self.iou)) if len(self.iou) else float("nan")

    @property
    def mean_f1(self) -> float:
        return float(np.mean(self.f1)) if len(self.f1) else float("nan")

    def to_json(self) -> dict:
        return {"cameras": list(self.cameras), "iou": np.round(self.iou, 4).tolist(),
                "f1": np.round(self.f1, 4).tolist(), "mean_iou": round(self.mean_iou, 4),
                "mean_f1": round(self.mean_f1, 4), "pooled_iou": round(self.pooled_iou, 4),
                "pooled_f1": round(self.pooled_f1, 4)}


def mask_scores(pred: np.ndarray, truth: np.ndarray, cameras: tuple[str, ...]) -> Scores:
    """IoU and F1 of boolean masks (V,H,W) per view and pooled. A view where both are empty scores 1."""
    pred, truth = np.asarray(pred, bool), np.asarray(truth, bool)
    if pred.shape != truth.shape:
        raise EvaluateError(f"predicted masks {pred.shape} and paint masks {truth.shape} differ in shape")
    inter = (pred & truth).reshape(len(pred), -1).sum(axis=1).astype(np.float64)
    p, t = pred.reshape(len(pred), -1).sum(axis=1), truth.reshape(len(truth), -1).sum(axis=1)
    union = p + t - inter
    iou = np.where(union > 0, inter / np.maximum(union, 1), 1.0)
    f1 = np.where(p + t > 0, 2 * inter / np.maximum(p + t, 1), 1.0)
    total = p.sum() + t.sum()
    return Scores(tuple(cameras), iou, f1, float(inter.sum() / max(total - inter.sum(), 1)),
                  float(2 * inter.sum() / max(total, 1)))


def pick_views(paint: np.ndarray, count: int = DEFAULT_VIEWS, min_px: int = MIN_PAINT_PX) -> np.ndarray:
    """Indices of the `count` views showing the most paint (at least min_px pixels), most first."""
    pixels = np.asarray(paint, bool).reshape(len(paint), -1).sum(axis=1)
    order = np.argsort(-pixels, kind="stable")
    order = order[pixels[order] >= min_px]
    if len(order) == 0:
        raise EvaluateError(f"no view shows at least {min_px} paint pixels: nothing to score contacts against")
    return order[:count]


def spread_cameras(rig: CameraRig, count: int) -> np.ndarray:
    """`count` camera indices spread over the rig (farthest-point order of the camera centres,
    starting from the first camera), in rig order: the subsets of the camera ablation."""
    centres = rig.centers
    if count >= len(rig):
        return np.arange(len(rig))
    chosen = [0]
    dist = np.linalg.norm(centres - centres[0], axis=1)
    for _ in range(count - 1):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(centres - centres[nxt], axis=1))
    return np.sort(np.array(chosen))


def to_raw_pixels(images: np.ndarray, rig: CameraRig) -> np.ndarray:
    """Images (V,H,W) rendered with each camera's pinhole K, resampled onto its raw (distorted) pixel grid."""
    out = np.empty_like(images, dtype=np.float32)
    for i, image in enumerate(images):
        h, w = image.shape
        if not np.any(rig.dist[i]):
            out[i] = image
            continue
        grid = np.stack(np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)), -1)
        # Newton's undistortion: OpenCV's default 5 fixed-point steps are pixels off near the
        # corners of a strongly barrel-distorted lens
        xy = undistort_points(rig.subset([rig.ids[i]]), grid.reshape(1, -1, 2))[0]
        K = rig.K[i]
        ideal = np.stack([K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2], K[1, 1] * xy[:, 1] + K[1, 2]], -1)
        ideal = np.nan_to_num(ideal, nan=-1.0).astype(np.float32).reshape(h, w, 2)
        out[i] = cv2.remap(image.astype(np.float32), ideal[..., 0], ideal[..., 1], cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out


def render_contacts(model: PosedModel, angles: np.ndarray, values: np.ndarray, rig: CameraRig,
                    supersample: int = SUPERSAMPLE) -> tuple[np.ndarray, np.ndarray]:
    """Contact value and coverage (V,H,W) of a posed model in the raw pixels of every camera of `rig`.

    Rendered `supersample` times finer and box-filtered down, so a pixel's coverage is the
    fraction of its area the hand covers, as in a label image, instead of a splat's footprint
    widened by the rasterizer's one-pixel low-pass."""
    sizes = {tuple(s) for s in np.asarray(rig.size, int)}
    if len(sizes) != 1:
        raise EvaluateError(f"ground-truth views of one size are needed, got {sorted(sizes)}")
    (w, h), = sizes
    s = int(supersample)
    K = torch.tensor(scale_intrinsics(rig.K, s), dtype=torch.float32)
    value, alpha = render_values(model, angles, values, world_to_camera(rig.R, rig.t), K, w * s, h * s)
    # both premultiplied: filter and resample them, then divide once
    shrink = np.stack([cv2.resize(np.stack([v, a], -1), (w, h), interpolation=cv2.INTER_AREA)
                       for v, a in zip(value, alpha)])
    raw_alpha = to_raw_pixels(shrink[..., 1], rig)
    return surface_value(to_raw_pixels(shrink[..., 0], rig), raw_alpha), raw_alpha


def score_contacts(model: PosedModel, canonical: np.ndarray, accumulated: np.ndarray, rig: CameraRig,
                   paint: np.ndarray, views: np.ndarray, threshold: float = THRESHOLD) -> tuple[Scores, np.ndarray]:
    """Scores of a grasp's accumulated contact (G,) rendered on the canonical pose (26,) into the
    views `views` (indices into rig and paint (C,H,W)); also the predicted masks (V,H,W)."""
    sub = rig.subset([rig.ids[i] for i in views])
    value, alpha = render_contacts(model, canonical, accumulated, sub)
    pred = (value >= threshold) & (alpha >= 0.5)
    return mask_scores(pred, np.asarray(paint, bool)[views], sub.ids), pred


def canonical_pose(angles: np.ndarray) -> np.ndarray:
    """One pose (26,) for a still canonical take: the median of its fitted frames."""
    angles = np.asarray(angles, dtype=np.float64)
    fitted = angles[np.all(np.isfinite(angles), axis=1)]
    if len(fitted) == 0:
        raise EvaluateError("the canonical take has no frame with a fitted hand")
    return np.median(fitted, axis=0)
