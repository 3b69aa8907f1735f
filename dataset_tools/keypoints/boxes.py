"""Hand boxes and crop rectangles.

A *box* is an axis-aligned hand box (x0, y0, x1, y1) in image pixels, as a user or an earlier stage
gives it. A *rect* is what a crop is cut from: (cx, cy, w, h, angle), centre and size in image
pixels and `angle` the direction of the crop's "up" in the image, in radians clockwise from
image-up: the crop's up axis is (sin angle, -cos angle) in image coordinates (y down). MediaPipe's
landmark model expects the hand upright, wrist at the bottom and fingers up, so its rects carry
the angle of the wrist -> middle-knuckle axis.

Pixel convention: OpenCV's, integer coordinates at pixel centres, in the image and in the crop.
"""

from __future__ import annotations

import warnings

import cv2
import numpy as np

from manus_core.cameras import CameraRig

WRIST, INDEX_MCP, MIDDLE_MCP, RING_MCP = 0, 5, 9, 13
# The joints MediaPipe re-crops from (wrist, thumb base, the knuckles and the first phalanges):
# fingertips wander the most, so they are left out of the extent.
RECT_JOINTS = np.array([0, 1, 2, 3, 5, 6, 9, 10, 13, 14, 17, 18])


def _as_boxes(boxes: np.ndarray) -> np.ndarray:
    boxes = np.asarray(boxes, dtype=np.float64)
    if boxes.ndim != 2 or boxes.shape[1] != 4:
        raise ValueError(f"boxes must be (N,4) x0,y0,x1,y1, got shape {boxes.shape}")
    return boxes


def rects_from_boxes(boxes: np.ndarray, scale: float = 1.0, aspect: float = 1.0,
                     angles: np.ndarray | None = None) -> np.ndarray:
    """Rects centred on the boxes, enlarged by `scale`, with width/height = `aspect` (N,5).

    The side that is too short for the aspect ratio is lengthened, so the rect always covers the box.
    """
    boxes = _as_boxes(boxes)
    centre = (boxes[:, :2] + boxes[:, 2:]) / 2
    w = np.abs(boxes[:, 2] - boxes[:, 0])
    h = np.abs(boxes[:, 3] - boxes[:, 1])
    w, h = np.maximum(w, h * aspect), np.maximum(h, w / aspect)
    angle = np.zeros(len(boxes)) if angles is None else np.broadcast_to(np.asarray(angles, float), len(boxes))
    return np.column_stack([centre, w * scale, h * scale, angle])


def hand_angle(keypoints: np.ndarray) -> np.ndarray:
    """Angle of the wrist -> knuckles axis (...,) for keypoints (...,21,2+), as in `rects`.

    The knuckle point averages the middle knuckle with the mean of the index and ring knuckles:
    steadier than the middle knuckle alone when one finger is mislocated.
    """
    kp = np.asarray(keypoints, dtype=np.float64)[..., :2]
    knuckles = ((kp[..., INDEX_MCP, :] + kp[..., RING_MCP, :]) / 2 + kp[..., MIDDLE_MCP, :]) / 2
    d = knuckles - kp[..., WRIST, :]
    return np.arctan2(d[..., 0], -d[..., 1])


def rects_from_keypoints(keypoints: np.ndarray, scale: float = 2.0, shift: float = -0.1,
                         joints: np.ndarray = RECT_JOINTS) -> np.ndarray:
    """Square rects around hands (N,21,2+) rotated to the hand axis (N,5), for re-cropping.

    The extent of `joints` is measured in the hand's rotated frame, the square side is its longer
    side times `scale`, and the centre moves by `shift` times the side along the crop's y axis
    (negative: towards the fingers, which the extent of the knuckles leaves out).
    """
    kp = np.asarray(keypoints, dtype=np.float64)[..., :2]
    angle = hand_angle(kp)
    c, s = np.cos(angle), np.sin(angle)
    # Crop axes in image coordinates: x = (cos, sin), y (down in the crop) = (-sin, cos).
    axes = np.stack([np.stack([c, s], -1), np.stack([-s, c], -1)], -2)  # (N,2,2) rows = axes
    local = np.einsum("nij,nkj->nki", axes, kp[:, joints])
    lo, hi = local.min(axis=1), local.max(axis=1)
    side = (hi - lo).max(axis=1) * scale
    centre_local = (lo + hi) / 2 + np.stack([np.zeros_like(side), shift * side], -1)
    centre = np.einsum("nji,nj->ni", axes, centre_local)
    return np.column_stack([centre, side, side, angle])


def affine_matrices(rects: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N,2,3) maps from image pixels to crop pixels (both pixel-centre conventions).

    The rect's extent covers the crop's extent exactly: rect edge to crop edge, so a rect of side
    w mapped to `width` pixels has w/width image pixels per crop pixel.
    """
    rects = np.asarray(rects, dtype=np.float64).reshape(-1, 5)
    cx, cy, w, h, angle = rects.T
    c, s = np.cos(angle), np.sin(angle)
    sx, sy = width / w, height / h
    A = np.empty((len(rects), 2, 3))
    A[:, 0, 0], A[:, 0, 1] = sx * c, sx * s
    A[:, 1, 0], A[:, 1, 1] = -sy * s, sy * c
    # Edge-to-edge mapping in corner coordinates, then shifted by half a pixel on both sides.
    corner_centre = np.stack([cx + 0.5, cy + 0.5], -1)
    offset = np.array([width / 2, height / 2]) - np.einsum("nij,nj->ni", A[:, :, :2], corner_centre)
    A[:, :, 2] = offset + np.einsum("nij,j->ni", A[:, :, :2], [0.5, 0.5]) - 0.5
    return A


def invert_affine(A: np.ndarray) -> np.ndarray:
    """Inverse of (N,2,3) affine maps."""
    L = np.linalg.inv(A[:, :, :2])
    return np.concatenate([L, -np.einsum("nij,nj->ni", L, A[:, :, 2])[:, :, None]], axis=2)


def apply_affine(A: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply (N,2,3) maps to points (N,K,2)."""
    return np.einsum("nij,nkj->nki", A[:, :, :2], points) + A[:, None, :, 2]


def crop(image: np.ndarray, rects: np.ndarray, width: int, height: int,
         border: int = cv2.BORDER_REPLICATE) -> tuple[np.ndarray, np.ndarray]:
    """Cut rotated rects out of one image: crops (N,height,width,C) and their maps (N,2,3).

    One cv2.warpAffine per rect: each is a single C call over the crop's pixels, and crops are few
    per image (the network, not the warp, is batched).
    """
    A = affine_matrices(rects, width, height)
    out = np.empty((len(A), height, width) + image.shape[2:], dtype=image.dtype)
    for i, M in enumerate(A):
        out[i] = cv2.warpAffine(image, M, (width, height), flags=cv2.INTER_LINEAR, borderMode=border)
    return out, A


def boxes_from_keypoints(keypoints: np.ndarray, min_confidence: float = 0.0) -> np.ndarray:
    """Axis-aligned boxes (...,4) around the keypoints (...,21,3) above `min_confidence`; NaN if none."""
    kp = np.asarray(keypoints, dtype=np.float64)
    valid = (kp[..., 2] > min_confidence) & np.isfinite(kp[..., :2]).all(-1)
    xy = np.where(valid[..., None], kp[..., :2], np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices: empty boxes are NaN
        return np.concatenate([np.nanmin(xy, axis=-2), np.nanmax(xy, axis=-2)], axis=-1)


def boxes_from_masks(masks: np.ndarray) -> np.ndarray:
    """Boxes (...,4) around the true pixels of masks (...,H,W) (pixel centres); NaN where empty."""
    masks = np.asarray(masks, dtype=bool)
    rows, cols = masks.any(axis=-1), masks.any(axis=-2)
    h, w = masks.shape[-2:]

    def extent(any_: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
        first = np.argmax(any_, axis=-1).astype(np.float64)
        last = (n - 1 - np.argmax(any_[..., ::-1], axis=-1)).astype(np.float64)
        empty = ~any_.any(axis=-1)
        return np.where(empty, np.nan, first), np.where(empty, np.nan, last)

    y0, y1 = extent(rows, h)
    x0, x1 = extent(cols, w)
    return np.stack([x0, y0, x1, y1], axis=-1)


def boxes_from_joints(rig: CameraRig, joints3d: np.ndarray,
                      min_visible: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Boxes (C,4) and hand angles (C,) of 3D hand joints (21,3) reprojected into a CameraRig.

    For joints (F,21,3): (F,C,4) and (F,C). Used to crop each view around the previous frame's
    triangulated hand, already turned to its axis (Detector.detect(image, boxes, angles)). A view
    gets NaN where fewer than `min_visible` joints land in front of the camera and inside its
    image; boxes are clipped to the image.
    """
    joints3d = np.asarray(joints3d, dtype=np.float64)
    single = joints3d.ndim == 2
    J = joints3d.reshape(-1, joints3d.shape[-2], 3)
    F, K = J.shape[:2]
    uv = rig.project(J.reshape(-1, 3)).reshape(len(rig), F, K, 2).transpose(1, 0, 2, 3)  # (F,C,K,2)
    size = np.asarray(rig.size, dtype=np.float64)[None, :, None, :]
    inside = np.isfinite(uv).all(-1) & (uv >= -0.5).all(-1) & (uv <= size - 0.5).all(-1)
    kp = np.concatenate([uv, inside[..., None].astype(np.float64)], axis=-1)
    boxes = boxes_from_keypoints(kp, min_confidence=0.5)
    seen = inside.sum(-1) >= min_visible
    boxes[~seen] = np.nan
    upper = np.tile(np.asarray(rig.size, dtype=np.float64) - 0.5, 2)  # (C,4): w, h, w, h
    boxes = np.clip(boxes, -0.5, upper)
    # The axis needs the wrist and knuckles in front of the camera, not necessarily inside the image.
    angles = np.where(seen, hand_angle(uv), np.nan)
    return (boxes[0], angles[0]) if single else (boxes, angles)
