"""Hand and object masks of one frame group (all views at once), from backgrounds and colours."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from manus_core.cameras import CameraRig
from manus_core.errors import SegmentationError

from .background import BackgroundModel, grow_window, remove_small
from .colour import ColourModel, PaintKey
from .edges import refine_edges
from .multiview import Window, consistent_masks

# edges.refine_edges' band (2) and its 5x5 dilation, the 3x3 windows of its pure colours, and a
# background border several pixels wide so that no image edge is mistaken for a mask's
EDGE_MARGIN = 12


def foreground_masks(images: np.ndarray, backgrounds: Sequence[BackgroundModel | None], min_area: int = 8,
                     gains: Sequence[float | None] | None = None) -> np.ndarray:
    """Foreground (C,H,W) of views (C,H,W,3); a view without a background gets an empty mask.
    gains: each view's brightness against its background, when known (BackgroundModel.gain)."""
    return _foreground(images, backgrounds, min_area, gains)[0]


def _foreground(images: np.ndarray, backgrounds: Sequence[BackgroundModel | None], min_area: int = 8,
                gains: Sequence[float | None] | None = None) -> tuple[np.ndarray, list[Window | None]]:
    """foreground_masks and each mask's box (None: empty)."""
    images = np.asarray(images)
    out = np.zeros(images.shape[:3], bool)
    boxes: list[Window | None] = [None] * len(images)
    gains = [None] * len(images) if gains is None else gains
    for c, (image, bg, gain) in enumerate(zip(images, backgrounds, gains)):
        if bg is not None:
            boxes[c] = bg.foreground_box(image, min_area=min_area, gain=gain, out=out[c])[1]
    return out, boxes


def object_pixels(images: np.ndarray, backgrounds: Sequence[BackgroundModel | None]) -> np.ndarray:
    """Pixels (N,3) of an object take's foreground (its object), eroded off the mixed edges."""
    masks = foreground_masks(images, backgrounds, min_area=20)
    kernel = np.ones((3, 3), np.uint8)
    inner = np.stack([cv2.erode(m.astype(np.uint8), kernel) > 0 for m in masks])
    if np.count_nonzero(inner) < 20:
        raise SegmentationError("object take: the object is not seen against the background in any view")
    return np.asarray(images, np.float32)[inner]


def object_colour(images: np.ndarray, backgrounds: Sequence[BackgroundModel | None]) -> ColourModel:
    """The object's colour model from frames of the object-only take (against the empty cube)."""
    return ColourModel.fit(object_pixels(images, backgrounds))


def paint_key_from_object(images: np.ndarray, backgrounds: Sequence[BackgroundModel | None]) -> PaintKey:
    """The paint colour from the painted object in the object take."""
    return PaintKey.from_pixels(object_pixels(images, backgrounds))


def _object_by_colour(images: np.ndarray, fg: np.ndarray, windows: Sequence[Window | None],
                      object_model: ColourModel) -> np.ndarray:
    """(C,H,W) foreground pixels more likely of the object's colour than of the skin's, looked for
    in each view's window around its foreground.

    The skin's colour model is learnt from this frame group's own foreground away from the
    object's colours (it follows the subject and the lights). Comparing the two likelihoods
    rather than thresholding the object's alone keeps the object's shaded edges, whose colour is
    rare in the object take but rarer still on skin."""
    kernel = np.ones((3, 3), np.uint8)
    views = [(c, w, images[c][w]) for c, w in enumerate(windows) if w is not None]
    matches = [object_model.matches(image) for _, _, image in views]
    skin_px = [(cv2.erode(fg[c][w].astype(np.uint8), kernel) > 0) & ~m for (c, w, _), m in zip(views, matches)]
    out = np.zeros_like(fg)
    if sum(np.count_nonzero(s) for s in skin_px) < 20:
        # (almost) all of the foreground is of the object's colour: nothing to compare with
        for (c, w, _), m in zip(views, matches):
            out[c][w] = m
        return out
    skin = ColourModel.fit(np.concatenate([image[s] for (_, _, image), s in zip(views, skin_px)]))
    for c, w, image in views:
        decision = object_model.likelihood(image) > skin.likelihood(image)
        out[c][w] = cv2.medianBlur(decision.astype(np.uint8), 3) > 0
    return out


def hand_object_masks(images: np.ndarray, backgrounds: Sequence[BackgroundModel | None],
                      rig: CameraRig | None = None, object_model: ColourModel | None = None,
                      min_area: int = 8) -> tuple[np.ndarray, np.ndarray, dict]:
    """Hand and object masks (C,H,W) of one frame group, and a report (with each view's
    `windows`: the masks are empty outside them; None where both are empty).

    Foreground against the empty cube; with a rig, made consistent across the views; split by
    colour: pixels more likely of the object's colour than of the skin's are object, the rest hand
    (without an object model, all foreground is hand); last, the pixels along every edge are
    unmixed against the background and the two classes (edges.refine_edges)."""
    gains = [None if bg is None else bg.gain(image) for image, bg in zip(images, backgrounds)]
    fg, boxes = _foreground(images, backgrounds, min_area, gains)
    report: dict = {}
    if rig is not None and sum(b is not None for b in boxes) >= 2:
        fg, report["multiview"] = consistent_masks(rig, fg, boxes=boxes)
        boxes = report["multiview"]["boxes"]
    images = np.asarray(images)
    # the colours and the edges are decided in a window around the foreground (a hand is a small
    # part of a 1280x720 view): every pixel they look at is in it, so the labels are the same
    windows = [None if b is None else grow_window(b, EDGE_MARGIN, fg.shape[1:]) for b in boxes]
    report["windows"] = windows
    is_object = None if object_model is None else _object_by_colour(images, fg, windows, object_model)
    obj = np.zeros(fg.shape, bool)
    # each view's window is read from fg before the hand's labels replace it there
    hand = fg
    for c, (image, window) in enumerate(zip(images, windows)):
        if window is None:
            continue
        labels = fg[c][window].astype(np.uint8)
        candidates = None if is_object is None else is_object[c][window] & fg[c][window]
        if candidates is not None and candidates.any():
            labels[remove_small(candidates, min_area)] = 2
        labels = refine_edges(image[window], labels, backgrounds[c].median[window], (1, 2), band=2, gain=gains[c])
        hand[c][window], obj[c][window] = labels == 1, labels == 2
    return hand, obj, report
