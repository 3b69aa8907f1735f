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

from manus_core.jit import jit

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
    ny, nx, dist = _nearest_pure(pure, at[0].astype(np.int64), at[1].astype(np.int64), _OFFSETS, _OFFSET_DISTANCES)
    return _window_means(image, pure, ny, nx), dist


def _chamfer_offsets(reach: float) -> tuple[np.ndarray, np.ndarray]:
    """The offsets (K,2) (rows, columns) within `reach` of a pixel in OpenCV's 5x5 chamfer
    distance (DIST_L2 with mask 5: steps 1, 1.4 and 2.1969), nearest first, and their distances
    (K,) float32 as its distance transform sums them."""
    n = int(np.ceil(reach)) + 1
    # each step of the mask in its eight orientations (mirrored, swapped), with its length
    steps = [(sy * a, sx * b, np.float32(length)) for u, v, length in ((0, 1, 1.0), (1, 1, 1.4), (1, 2, 2.1969))
             for a, b in {(u, v), (v, u)} for sy in (-1, 1) for sx in (-1, 1)]
    best = {(0, 0): np.float32(0)}
    frontier = [(0, 0)]
    while frontier:   # shortest paths over the steps (the grid is a few pixels across)
        grown = []
        for y, x in frontier:
            for dy, dx, w in steps:
                q, d = (y + dy, x + dx), best[y, x] + w
                if max(abs(q[0]), abs(q[1])) <= n and d < best.get(q, np.float32(np.inf)):
                    best[q] = d
                    grown.append(q)
        frontier = grown
    kept = sorted((d, q) for q, d in best.items() if d <= reach)
    return (np.array([q for _, q in kept], np.int64).reshape(-1, 2),
            np.array([d for d, _ in kept], np.float32))


# (pixels further than REACH from a class's pure pixels may not take its colour: only those are looked for)
_OFFSETS, _OFFSET_DISTANCES = _chamfer_offsets(REACH)


@jit
def _nearest_pure(pure: np.ndarray, ys: np.ndarray, xs: np.ndarray, offsets: np.ndarray,
                  distances: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each pixel's (ys, xs) nearest pure pixel among `offsets` (nearest first) and its distance;
    none there: the pixel itself at an infinite distance. (OpenCV's distance transform with labels
    of the whole window, for the few pixels of its edges, was a fifth of refine_edges' time.)"""
    h, w = pure.shape
    ny, nx = ys.copy(), xs.copy()
    dist = np.full(len(ys), np.inf, np.float32)
    for i in range(len(ys)):
        for k in range(len(offsets)):
            y, x = ys[i] + offsets[k, 0], xs[i] + offsets[k, 1]
            if 0 <= y < h and 0 <= x < w and pure[y, x]:
                ny[i], nx[i], dist[i] = y, x, distances[k]
                break
    return ny, nx, dist


@jit
def _window_means(image: np.ndarray, pure: np.ndarray, ny: np.ndarray, nx: np.ndarray) -> np.ndarray:
    """(N,3) the mean colour of the pure pixels in the 3x3 window around each (ny, nx), itself a
    pure pixel; an image edge mirrored as OpenCV's box filter does (BORDER_REFLECT_101). Two box
    filters of the whole window, for the few pixels of the edges, were half of _pure_colours' time."""
    h, w = pure.shape
    out = np.zeros((len(ny), 3), np.float32)
    for i in range(len(ny)):
        if not pure[ny[i], nx[i]]:   # (no pure pixel near: a colour that no pair may use)
            continue
        count = np.float32(0)
        for dy in range(-1, 2):
            y = abs(ny[i] + dy)
            y = max(2 * (h - 1) - y, 0) if y > h - 1 else y
            for dx in range(-1, 2):
                x = abs(nx[i] + dx)
                x = max(2 * (w - 1) - x, 0) if x > w - 1 else x
                if pure[y, x]:
                    count += 1
                    for c in range(3):
                        out[i, c] += image[y, x, c]
        for c in range(3):
            out[i, c] /= count
    return out


def refine_edges(image: np.ndarray, labels: np.ndarray, background: np.ndarray | None,
                 classes: tuple[int, ...], band: int = 1, thin: tuple[int, ...] = (), gain: float = 1.0) -> np.ndarray:
    """Labels (H,W) with the pixels within `band` px of an edge re-decided by unmixing.

    image (H,W,3) and background (H,W,3) (the background's colour at the image's brightness, or at
    its own times `gain`, which is applied to the few pixels that need it; None where there is no
    background to mix with, e.g. inside a hand mask) as float; labels (H,W) int with 0 for the
    background and the given `classes`. A pixel of the band may go to any class
    whose pure pixels are within REACH of it; the classes in `thin` (found by a colour key) lend
    their thin parts' own colours (see _pure_colours), and their mean colour further away."""
    # colours are compared in YCrCb (_ycc), a linear map: each pixel and mean colour is mapped when
    # it is needed, not the whole window (a fifth of refine_edges' time at 1280x720)
    image = np.asarray(image)
    labels = np.asarray(labels)
    present = [k for k in classes if np.any(labels == k)]
    if not present:
        return labels.copy()
    size = 2 * band + 1
    kernel = np.ones((size, size), np.uint8)
    # on an edge: a pixel whose neighbourhood is not all of one label, its largest and smallest
    # label differ (one dilation and one erosion, where each label's own took two of each)
    values = labels.astype(np.uint8, copy=False)
    edge = cv2.dilate(values, kernel) != cv2.erode(values, kernel, borderType=cv2.BORDER_REPLICATE)
    if background is None:
        edge &= labels != 0
    # (np.nonzero of a 2-D mask takes four times as long)
    ys, xs = np.divmod(np.flatnonzero(edge), edge.shape[1])
    if not len(ys):
        return labels.copy()
    ends, names = [], []
    if background is not None:
        ends.append(_ycc(np.asarray(background, np.float32)[ys, xs][None] * np.float32(gain))[0])
        names.append(0)
    near = []
    for k in present:
        colour, dist = _pure_colours(image, labels, k, k in thin, (ys, xs))
        colour = _ycc(colour)
        close = dist <= REACH
        if k in thin:
            # a keyed colour is the same all over: far from the class's pixels (paint seen edge-on
            # along a silhouette) its mean colour stands in
            colour[~close] = _ycc(image[labels == k].mean(axis=0, dtype=np.float32)[None])[0]
            close[:] = True
        ends.append(colour)
        names.append(k)
        near.append(close)
    reachable = np.stack(([np.ones(len(ys), bool)] if background is not None else []) + near)
    # every pair of ends, each at every shade: each pixel's distance to the segment between the two
    # colours. A class with itself is one pair, its brightest shade to its darkest: the shades lie on
    # one line through black, so that segment holds every pixel between two of them, and either end
    # names the class. (i, j, shade of i, shade of j) a pair, the first to explain a pixel best wins
    shades = [SHADES if n else (1.0,) for n in names]
    pairs = []
    for i in range(len(ends)):
        pairs.append((i, i, shades[i][0], shades[i][-1]))
        pairs += [(i, j, x, y) for j in range(i + 1, len(ends)) for x in shades[i] for y in shades[j]]
    table = np.array(pairs, np.float64)
    out = labels.copy()
    ends = np.ascontiguousarray(np.stack(ends).transpose(0, 2, 1))   # (E,3,N): each channel's pixels in a row
    pixel = np.ascontiguousarray(_ycc(image[ys, xs]).T)   # (3,N): each channel's pixels in a row
    _unmix(pixel, ys.astype(np.int64), xs.astype(np.int64), ends, reachable, table[:, :2].astype(np.int64),
           table[:, 2:].astype(np.float32), np.asarray(names, out.dtype), out)
    return out


@jit
def _unmix(pixel: np.ndarray, ys: np.ndarray, xs: np.ndarray, ends: np.ndarray, reachable: np.ndarray,
           pairs: np.ndarray, shades: np.ndarray, names: np.ndarray, out: np.ndarray) -> None:
    """refine_edges' decision at each pixel (ys, xs) of `out`, whose colours are `pixel` (3,N): of
    the pairs (i, j) of ends (E,3,N) at their shades, both reachable from the pixel, the first whose
    segment lies nearest the pixel's colour names it, by the end that makes up more than half of it
    (out[y, x] = that end's name); a pixel no pair may explain keeps its label. Pair after pair over all the pixels:
    the loop over the pixels runs in SIMD, six times as fast as each pixel's pairs in turn (and
    numpy's (pairs, N) arrays of every product took a third of refine_edges' time)."""
    count = len(ys)
    best = np.full(count, np.inf, np.float32)
    label = np.full(count, -1, np.int64)
    tiny = np.float32(1e-6)
    zero, one, half = np.float32(0), np.float32(1), np.float32(0.5)
    for k in range(len(pairs)):
        i, j = pairs[k, 0], pairs[k, 1]
        f, g = shades[k, 0], shades[k, 1]
        name_i, name_j = names[i], names[j]
        for n in range(count):
            b0, b1, b2 = ends[j, 0, n] * g, ends[j, 1, n] * g, ends[j, 2, n] * g
            a0, a1, a2 = ends[i, 0, n] * f - b0, ends[i, 1, n] * f - b1, ends[i, 2, n] * f - b2
            o0, o1, o2 = pixel[0, n] - b0, pixel[1, n] - b1, pixel[2, n] - b2
            length2 = max(a0 * a0 + a1 * a1 + a2 * a2, tiny)
            t = min(max((o0 * a0 + o1 * a1 + o2 * a2) / length2, zero), one)
            o0, o1, o2 = o0 - t * a0, o1 - t * a1, o2 - t * a2
            residual = o0 * o0 + o1 * o1 + o2 * o2
            # (no branch before the store: the loop stays in SIMD)
            if reachable[i, n] & reachable[j, n] & (residual < best[n]):
                best[n] = residual
                label[n] = name_i if t > half else name_j
    for n in range(count):
        if label[n] >= 0:
            out[ys[n], xs[n]] = label[n]
