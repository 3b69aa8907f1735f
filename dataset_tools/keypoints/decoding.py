"""Decoding of keypoint network outputs into input-pixel coordinates and confidences.

Coordinates come out in the network input's pixels with OpenCV's convention (integer coordinates
at pixel centres), the convention the crop maps of `boxes.affine_matrices` use.

- SimCC (RTMPose): one 1-D classification per axis, `split_ratio` bins per input pixel; bin b is
  input coordinate b / split_ratio. Confidence: the smaller of the two axis maxima, as RTMPose does
  (a joint is only as sure as its less certain axis).
- Heatmaps: one map per joint at a stride of input/heatmap pixels; heatmap pixel j covers input
  pixels [j*stride, (j+1)*stride), so its centre is input coordinate (j + 0.5) * stride - 0.5.
  Confidence: the peak value. Sub-pixel refinement: none, `quarter` (a quarter heatmap pixel
  towards the higher neighbour, the classic stacked-hourglass rule) or `parabola` (the vertex of the
  parabola through the peak and its two neighbours, per axis; exact for separable quadratic peaks).
  A peak on the map's border stays where it is.
"""

from __future__ import annotations

import numpy as np

REFINES = ("none", "quarter", "parabola")


def softmax(x: np.ndarray, axis: int = -1) -> np.ndarray:
    e = np.exp(x - x.max(axis=axis, keepdims=True))
    return e / e.sum(axis=axis, keepdims=True)


def decode_simcc(simcc_x: np.ndarray, simcc_y: np.ndarray, split_ratio: float = 2.0,
                 normalize: bool = False) -> np.ndarray:
    """(N,K,Wb), (N,K,Hb) SimCC logits -> (N,K,3) [x, y, confidence] in input pixels."""
    simcc_x = np.asarray(simcc_x, dtype=np.float32)
    simcc_y = np.asarray(simcc_y, dtype=np.float32)
    if simcc_x.ndim != 3 or simcc_y.ndim != 3 or simcc_x.shape[:2] != simcc_y.shape[:2]:
        raise ValueError(f"SimCC outputs must be (N,K,W*r) and (N,K,H*r), got {simcc_x.shape} and "
                         f"{simcc_y.shape}")
    if normalize:
        simcc_x, simcc_y = softmax(simcc_x), softmax(simcc_y)
    bx, by = simcc_x.argmax(-1), simcc_y.argmax(-1)
    conf = np.minimum(simcc_x.max(-1), simcc_y.max(-1))
    return np.stack([bx / split_ratio, by / split_ratio, conf], axis=-1).astype(np.float64)


def decode_heatmaps(heatmaps: np.ndarray, input_size: tuple[int, int], refine: str = "quarter",
                    sigmoid: bool = False) -> np.ndarray:
    """(N,K,h,w) heatmaps -> (N,K,3) [x, y, confidence] in input pixels; input_size = (width, height)."""
    hm = np.asarray(heatmaps, dtype=np.float64)
    if hm.ndim != 4:
        raise ValueError(f"heatmaps must be (N,K,h,w), got {hm.shape}")
    if refine not in REFINES:
        raise ValueError(f"refine must be one of {REFINES}, got {refine!r}")
    if sigmoid:
        hm = 1 / (1 + np.exp(-hm))
    N, K, h, w = hm.shape
    flat = hm.reshape(N, K, h * w).argmax(-1)
    iy, ix = np.divmod(flat, w)
    conf = np.take_along_axis(hm.reshape(N, K, h * w), flat[..., None], -1)[..., 0]
    x, y = ix.astype(np.float64), iy.astype(np.float64)
    if refine != "none":
        n, k = np.meshgrid(np.arange(N), np.arange(K), indexing="ij")

        def at(yy: np.ndarray, xx: np.ndarray) -> np.ndarray:
            return hm[n, k, np.clip(yy, 0, h - 1), np.clip(xx, 0, w - 1)]

        # A peak on the border has a neighbour missing on one side: it stays where it is.
        inner_x = (ix > 0) & (ix < w - 1)
        inner_y = (iy > 0) & (iy < h - 1)
        x += np.where(inner_x, _offset(at(iy, ix - 1), conf, at(iy, ix + 1), refine), 0.0)
        y += np.where(inner_y, _offset(at(iy - 1, ix), conf, at(iy + 1, ix), refine), 0.0)
    stride_x, stride_y = input_size[0] / w, input_size[1] / h
    return np.stack([(x + 0.5) * stride_x - 0.5, (y + 0.5) * stride_y - 0.5, conf], axis=-1)


def _offset(before: np.ndarray, peak: np.ndarray, after: np.ndarray, refine: str) -> np.ndarray:
    if refine == "quarter":
        return 0.25 * np.sign(after - before)
    curvature = before - 2 * peak + after
    with np.errstate(divide="ignore", invalid="ignore"):
        vertex = np.where(curvature < 0, 0.5 * (before - after) / curvature, 0.0)
    return np.clip(vertex, -0.5, 0.5)
