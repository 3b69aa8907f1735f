"""Pixel-exact edges of label maps by unmixing the mixed pixels along them.

At a test resolution a finger is a few pixels wide and a paint patch a few pixels across: most
of their pixels lie on an edge and are mixtures of two surfaces. A threshold on the difference to
the background takes in every pixel with a sliver of foreground, and a colour model takes a
half-skin, half-wall pixel for neither class. Each pixel of the band along the edges is modelled
as a mix I = a X + (1 - a) Y of two of the colours that meet there: the background's (known per
pixel) and each class's own, taken from the nearest pure pixels of that class. The pair that
explains the pixel best wins, and the pixel goes to the colour that makes up more than half of it
(the per-pixel truth of a renderer or an annotator counts a pixel for the majority of it).
"""

from __future__ import annotations

import cv2
import numpy as np

# How far (px) from a class's pure pixels a mixed pixel may take that class's colour.
REACH = 3.0
# Colours are compared in YCrCb with the chroma down-weighted: frames stored 4:2:0 keep chroma at half
# resolution, so an edge pixel's chroma is smeared over its neighbours and only its luma is sharp.
WEIGHTS = np.array([1.0, 0.4, 0.4], np.float32)
# A surface turns darker towards its silhouette (it faces away from the light there), so the
# foreground part of an edge pixel may be darker than the class's pure pixels further in.
SHADES = (1.0, 0.8, 0.65)


# BGR -> (Y, Cr, Cb) of JPEG without the offset of 128, so that shading scales all three alike
_YCC = np.array([[0.114, 0.587, 0.299], [-0.0813, -0.4187, 0.5], [0.5, -0.3313, -0.1687]], np.float32)


def _ycc(image: np.ndarray) -> np.ndarray:
    # OpenCV's transform is 3x faster than numpy's matrix product over the last axis
    image = np.asarray(image, np.float32)
    return cv2.transform(image.reshape(-1, 1, 3), _YCC * WEIGHTS[:, None]).reshape(image.shape)


def _pure_colours(image: np.ndarray, labels: np.ndarray, k: int, thin: bool, at: tuple[np.ndarray, np.ndarray]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """At the pixels `at` (rows (N,), columns (N,)), the colour (N,3) of class k's nearest pure
    pixels and the distance (N,) to them.

    Pure pixels are those whose 3x3 neighbourhood is all class k (no mixing). A thin part of the
    class (no pure pixel within 2 px) counts as pure only when `thin` is set, or when the class has
    no pure pixel at all: a thin strip named by a colour model is often a misnamed edge of another
    class and must not vouch for its own colour, but a strip found by a colour key (paint streaks)
    is what it is. The colour is the mean over the pure pixels of a 3x3 window, so that noise and
    texture average out."""
    own = labels == k
    pure = cv2.erode(own.astype(np.uint8), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE) > 0
    if not pure.any():
        pure = own
    elif thin:
        pure |= own & (cv2.distanceTransform((~pure).astype(np.uint8), cv2.DIST_L2, 3) > 2)
    dist, idx = cv2.distanceTransformWithLabels((~pure).astype(np.uint8), cv2.DIST_L2, 5,
                                                labelType=cv2.DIST_LABEL_PIXEL)
    # idx numbers the zero (pure) pixels in row-major order, from 1
    flat = np.flatnonzero(pure)
    ny, nx = np.divmod(flat[np.clip(idx[at] - 1, 0, len(flat) - 1)], pure.shape[1])
    mask = pure.astype(np.uint8)
    weight = cv2.blur(mask.astype(np.float32), (3, 3))[ny, nx]
    # the pure pixels' colours, others zero: OpenCV's masked copy (a product with the mask converted it
    # to floats and multiplied every channel)
    pure_image = cv2.copyTo(image, mask, np.zeros_like(image))
    mean = cv2.blur(pure_image, (3, 3))[ny, nx] / np.maximum(weight, 1e-6)[:, None]
    return mean, dist[at]


def refine_edges(image: np.ndarray, labels: np.ndarray, background: np.ndarray | None,
                 classes: tuple[int, ...], band: int = 1, thin: tuple[int, ...] = ()) -> np.ndarray:
    """Labels (H,W) with the pixels within `band` px of an edge re-decided by unmixing.

    image (H,W,3) and background (H,W,3) (the background's colour at the image's brightness; None
    where there is no background to mix with, e.g. inside a hand mask) as float; labels (H,W) int
    with 0 for the background and the given `classes`. A pixel of the band may go to any class
    whose pure pixels are within REACH of it; the classes in `thin` (found by a colour key) lend
    their thin parts' own colours (see _pure_colours), and their mean colour further away."""
    image = _ycc(np.asarray(image, np.float32))
    labels = np.asarray(labels)
    present = [k for k in classes if np.any(labels == k)]
    if not present:
        return labels.copy()
    size = 2 * band + 1
    kernel = np.ones((size, size), np.uint8)
    edge = np.zeros(labels.shape, bool)
    for k in ([0] if background is not None else []) + present:
        own = (labels == k).astype(np.uint8)
        edge |= (cv2.dilate(own, kernel) > 0) & (cv2.erode(own, kernel, borderType=cv2.BORDER_REPLICATE) == 0)
    if background is None:
        edge &= labels != 0
    ys, xs = np.nonzero(edge)
    if not len(ys):
        return labels.copy()
    pixel = image[ys, xs]
    ends, names = [], []
    if background is not None:
        ends.append(_ycc(np.asarray(background, np.float32)[ys, xs][None])[0])
        names.append(0)
    near = []
    for k in present:
        colour, dist = _pure_colours(image, labels, k, k in thin, (ys, xs))
        close = dist <= REACH
        if k in thin:
            # a keyed colour is the same all over: far from the class's pixels (paint seen edge-on
            # along a silhouette) its mean colour stands in
            colour[~close] = image[labels == k].mean(axis=0)
            close[:] = True
        ends.append(colour)
        names.append(k)
        near.append(close)
    reachable = np.stack(([np.ones(len(ys), bool)] if background is not None else []) + near)
    # every pair of ends, each at every shade: each pixel's distance to the segment between the two
    # colours, (K, N) for K pairs. A class with itself is one pair, its brightest shade to its
    # darkest: the shades lie on one line through black, so that segment holds every pixel between
    # two of them, and either end names the class. Colours are (3, N), a channel a row, so that the
    # products run over contiguous rows (over (N, 3) they strode through every pixel's three values)
    shaded = [[np.ascontiguousarray(e.T) * np.float32(f) for f in (SHADES if n else (1.0,))]
              for e, n in zip(ends, names)]
    pairs = []
    for i in range(len(ends)):
        pairs.append((i, i, shaded[i][0], shaded[i][-1]))
        pairs += [(i, j, x, y) for j in range(i + 1, len(ends)) for x in shaded[i] for y in shaded[j]]
    first = np.array([names[i] for i, _, _, _ in pairs])
    second = np.array([names[j] for _, j, _, _ in pairs])
    px = np.ascontiguousarray(pixel.T)
    a = np.empty((len(pairs), len(ys)), np.float32)
    residual = np.empty_like(a)
    for k, (i, j, end, begin) in enumerate(pairs):
        axis = end - begin
        offset = px - begin
        length2 = np.maximum(axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2], 1e-6)
        t = np.clip((offset[0] * axis[0] + offset[1] * axis[1] + offset[2] * axis[2]) / length2, 0.0, 1.0)
        offset -= t * axis
        a[k] = t
        residual[k] = offset[0] * offset[0] + offset[1] * offset[1] + offset[2] * offset[2]
        residual[k, ~(reachable[i] & reachable[j])] = np.inf
    # the first pair that explains the pixel best; a pixel no pair may explain keeps its label
    best = np.argmin(residual, axis=0)
    column = np.arange(len(ys))
    explained = np.isfinite(residual[best, column])
    out_label = labels[ys, xs].copy()
    out_label[explained] = np.where(a[best, column] > 0.5, first[best], second[best])[explained]
    out = labels.copy()
    out[ys, xs] = out_label
    return out
