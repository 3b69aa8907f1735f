"""Green paint on the hand: per-view contact masks and a contact value per hand surface point."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from manus_core.cameras import CameraRig
from manus_core.errors import SegmentationError

from .background import remove_small
from .colour import PaintKey, chromaticity
from .edges import refine_edges
from .multiview import pixels


def paint_masks(images: np.ndarray, hand_masks: np.ndarray, key: PaintKey, min_area: int = 3,
                backgrounds: Sequence[np.ndarray | None] | None = None) -> tuple[np.ndarray, dict]:
    """Paint masks (C,H,W) inside the hand masks of views (C,H,W,3), and a report.

    The skin colour to unmix against is the hand's own (its pixels far from the paint colour),
    so it follows the subject and the lights. The edges of the paint are then unmixed pixel by
    pixel (edges.refine_edges) against the skin and, given `backgrounds` ((H,W,3) per view at the
    images' brightness, None for a view without one), against the background: paint seen edge-on along a
    finger's silhouette is a sliver mixed with the wall behind it. `report["warnings"]` says when
    no paint is seen."""
    images = np.asarray(images, np.float32)
    hand_masks = np.asarray(hand_masks, bool)
    chroma = chromaticity(images)
    far = np.linalg.norm(chroma - key.colour, axis=-1) > 3 * key.spread + 0.03
    skin = hand_masks & far
    if np.count_nonzero(skin) < 20:
        raise SegmentationError(f"paint: only {np.count_nonzero(skin)} hand pixels of skin colour; "
                                "no hand to find paint on")
    base = np.median(chroma[skin], axis=0)
    out = np.zeros(hand_masks.shape, bool)
    for c in range(len(images)):
        if hand_masks[c].any():
            labels = np.where(key.mask(images[c], base, hand_masks[c]), 3, hand_masks[c].astype(np.uint8))
            background = None if backgrounds is None else backgrounds[c]
            refined = refine_edges(images[c], labels, background, (1, 3), thin=(3,)) == 3
            out[c] = remove_small(refined & cv2.dilate(hand_masks[c].astype(np.uint8), np.ones((3, 3), np.uint8)) > 0,
                                  min_area)
    counts = out.reshape(len(out), -1).sum(axis=1)
    report = {"paint_px": counts.tolist(), "skin_chromaticity": base.round(4).tolist(),
              "paint_chromaticity": np.asarray(key.colour).round(4).tolist(), "warnings": []}
    if not counts.any():
        report["warnings"].append("no paint colour found on the hand in any view (wrong colour, or no contact)")
    return out, report


def contact_votes(rig: CameraRig, points: np.ndarray, paint: np.ndarray, hand: np.ndarray | None = None,
                  normals: np.ndarray | None = None, depth_tolerance: float = 0.004) -> tuple[np.ndarray, np.ndarray]:
    """Contact value per hand surface point by voting of the views, and the number of voters.

    points (N,3), normals (N,3) optional, paint and hand masks (C,H,W). A view votes for a point
    when the point is in front of everything else of the hand there (a z-buffer of the points,
    min-filtered so that gaps between points do not let hidden ones through), faces the camera
    (with normals), and lies in the view's hand mask (when given). The value is the share of
    voters that see paint (NaN: no view sees the point)."""
    points = np.asarray(points, np.float64)
    paint = np.asarray(paint, bool)
    n_cam, h, w = paint.shape
    if n_cam != len(rig.ids):
        raise SegmentationError(f"contact votes: {n_cam} paint masks for {len(rig.ids)} cameras")
    uv = pixels(rig, points)
    cam_points = np.einsum("cij,nj->cni", rig.R, points) + rig.t[:, None, :]
    yes = np.zeros(len(points), np.int32)
    voters = np.zeros(len(points), np.int32)
    for c in range(n_cam):
        x, y, z = uv[c, :, 0], uv[c, :, 1], cam_points[c, :, 2]
        ok = (z > 1e-3) & (x >= 0) & (y >= 0) & (x < w) & (y < h)
        zbuf = np.full((h, w), np.inf, np.float32)
        np.minimum.at(zbuf, (y[ok], x[ok]), z[ok].astype(np.float32))
        zbuf = cv2.erode(zbuf, np.ones((3, 3), np.uint8))
        ok[ok] &= z[ok] <= zbuf[y[ok], x[ok]] + depth_tolerance
        if normals is not None:
            # a normal pointing away from the camera: the point is on the far side of its finger
            ok &= (np.einsum("ij,nj->ni", rig.R[c], np.asarray(normals, np.float64)) * cam_points[c]).sum(axis=1) < 0
        if hand is not None:
            ok[ok] &= np.asarray(hand[c], bool)[y[ok], x[ok]]
        voters += ok
        yes[ok] += paint[c][y[ok], x[ok]]
    with np.errstate(invalid="ignore", divide="ignore"):
        value = np.where(voters > 0, yes / np.maximum(voters, 1), np.nan)
    return value, voters
