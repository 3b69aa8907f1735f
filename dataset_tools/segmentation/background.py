"""Per-camera background models and foreground masks (DESIGN.md stage 5).

A background is the per-pixel median of a few frames of a take without the hand (the empty
cube, or the object alone), so a passing glitch or the sensor noise of one frame does not
enter it; the per-pixel noise is the median absolute deviation of the same frames. The LED
level scales a whole frame (the simulated cube: 0.25 + 0.75 * level), so each frame is first
brought to the background's brightness by a robust gain before it is compared.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from manus_core.errors import SegmentationError
from manus_core.jit import jit

# The MAD of a few JPEG frames underestimates the noise of a new frame: a floor in grey levels.
NOISE_FLOOR = 2.5
# Colour differences this many noise sigmas above the background count as foreground.
THRESHOLD_SIGMA = 3.0
# Shading of the background changes by a few percent with the LED level (JPEG, clipping):
# a relative tolerance keeps bright walls from turning into foreground.
RELATIVE_TOLERANCE = 0.03
# The gain is the median ratio over a regular grid of about this many pixels: at 1280x720 every
# 8th row and column, at 320x180 every 2nd. Each pixel's ratio is the gain within a percent or two
# (sensor noise against channel sums of 100 or more), so the median of 14,400 is good to ~1e-4;
# the 57,600 of every 4th row and column cost 0.76 ms a view at 1280x720.
GAIN_SAMPLES = 12_500
# Images this many rows high or more are first compared in blocks (1280x720: 4x4 px), so that the
# per-pixel work is done only around the foreground: a hand is a few percent of a 1280x720 view.
COARSE_HEIGHT = 180
# A block counts when its mean differs by this share of the per-pixel threshold: a finger two
# pixels wide across a 4x4 block moves its mean by half its own difference.
BLOCK_SHARE = 0.4
# More separate windows than this (noise all over a view): one window around them all.
MAX_WINDOWS = 32


@dataclass(frozen=True)
class BackgroundModel:
    """One camera's background: median image (H,W,3) float32 and noise sigma (H,W) float32."""

    median: np.ndarray
    sigma: np.ndarray

    @classmethod
    def fit(cls, frames: np.ndarray) -> "BackgroundModel":
        """Fit from frames (N,H,W,3) (uint8 or float 0..255) of one camera, gain-normalised first.
        Meant for a few frames (segment reads 5): the per-pixel sort takes N rounds over them, so its
        cost grows with N squared (5 frames of 1280x720: 40 ms; 50 would take some seconds)."""
        frames = np.asarray(frames)
        if frames.ndim != 4 or frames.shape[-1] != 3 or len(frames) == 0:
            raise SegmentationError(f"background: expected frames (N,H,W,3), got shape {frames.shape}")
        if frames.dtype != np.uint8:
            frames = frames.astype(np.float32)
        # each frame's gain against the frames' median, which the gain reads on its grid only
        step = _gain_step(frames[0])
        first = channel_sum(median_of_frames(frames[:, ::step, ::step].astype(np.float32)))
        gains = np.array([_gain(f, step, first) for f in frames], np.float32)
        median, mad = _fit_kernel(frames, gains)
        return cls(median, np.maximum(mad, np.float32(NOISE_FLOOR)))

    @property
    def shape(self) -> tuple[int, int]:
        return self.median.shape[:2]

    def gain(self, image: np.ndarray) -> float:
        """The brightness of `image` relative to the background's (_gain; the background's side of
        it is computed once)."""
        step = _gain_step(image)
        if self.__dict__.get("_gain_reference", (None,))[0] != step:
            self.__dict__["_gain_reference"] = step, channel_sum(self.median[::step, ::step])
        return _gain(image, step, self.__dict__["_gain_reference"][1])

    def at_brightness(self, image: np.ndarray) -> np.ndarray:
        """The background's colours (H,W,3) float32 at the brightness (LED level) of `image`."""
        return self.median * np.float32(self.gain(image))

    def difference(self, image: np.ndarray) -> np.ndarray:
        """Per-pixel colour difference (H,W) to the background in noise sigmas, after the gain."""
        self._check(image)
        whole = (slice(0, image.shape[0]), slice(0, image.shape[1]))
        return np.sqrt(self._score2(image, 1 / self.gain(image), whole))

    def foreground(self, image: np.ndarray, threshold: float = THRESHOLD_SIGMA, min_area: int = 0,
                   block: int | None = None, gain: float | None = None, out: np.ndarray | None = None) -> np.ndarray:
        """Boolean foreground mask (H,W): different from the background, small specks removed.

        The image is first compared with the background in blocks of `block` px (default: larger
        images in blocks, see COARSE_HEIGHT); only around the blocks that differ is the difference
        computed per pixel, so the cost follows the foreground's area, not the image's. Inside
        those windows the mask is the per-pixel one exactly; a foreground too faint and small to
        move a block's mean by THRESHOLD_SIGMA * BLOCK_SHARE is not looked for. `gain`: the image's
        (self.gain), when known. `out`: an (H,W) bool array of zeros to write the mask into (a
        frame group's masks, written only where its windows are)."""
        return self.foreground_box(image, threshold, min_area, block, gain, out)[0]

    def foreground_box(self, image: np.ndarray, threshold: float = THRESHOLD_SIGMA, min_area: int = 0,
                       block: int | None = None, gain: float | None = None,
                       out: np.ndarray | None = None) -> tuple[np.ndarray, tuple[slice, slice] | None]:
        """foreground() and the mask's bounding box (bounding_window(mask, 0)), found in the windows
        looked at (a pass over a whole 1280x720 view's mask cost as much as the hand's pixels)."""
        self._check(image)
        inverse_gain = 1 / (self.gain(image) if gain is None else gain)
        block = max(1, self.shape[0] // COARSE_HEIGHT) if block is None else int(block)
        mask = np.zeros(self.shape, bool) if out is None else out
        windows = self._windows(image, inverse_gain, threshold, block) if block > 1 else [
            (slice(0, self.shape[0]), slice(0, self.shape[1]))]
        for rows, cols in windows:
            # one pixel more on each side for the 3x3 median, dropped again
            outer = (slice(max(rows.start - 1, 0), rows.stop + 1), slice(max(cols.start - 1, 0), cols.stop + 1))
            # a 3x3 median of the score (not of the mask) keeps thin fingers but drops single-pixel
            # noise; the squared score has the same median order
            found = cv2.medianBlur(self._score2(image, inverse_gain, outer), 3) > np.float32(threshold ** 2)
            inner = (slice(rows.start - outer[0].start, rows.stop - outer[0].start),
                     slice(cols.start - outer[1].start, cols.stop - outer[1].start))
            mask[rows, cols] |= found[inner]
        if not windows:
            return mask, None
        around = _union(windows)
        if min_area:
            mask[around] = remove_small(mask[around], min_area)
        return mask, window_box(mask[around], around)

    def _check(self, image: np.ndarray) -> None:
        if image.shape != self.median.shape:
            raise SegmentationError(f"image of shape {image.shape} against a background of shape {self.median.shape}")

    def _score2(self, image: np.ndarray, inverse_gain: float, window: tuple[slice, slice]) -> np.ndarray:
        """The squared difference (h,w) float32 in noise sigmas over `window` of the image."""
        return _score2_kernel(image[window], self.median[window], self.sigma[window], np.float32(inverse_gain),
                              np.float32(RELATIVE_TOLERANCE))

    def _windows(self, image: np.ndarray, inverse_gain: float, threshold: float,
                 block: int) -> list[tuple[slice, slice]]:
        """Windows (rows, columns) around the blocks whose mean colour differs from the
        background's: block means by area averaging, scored against the block means of the
        background with its per-pixel noise (conservative: averaging lowers the noise), grown
        by one block so that a block the foreground only grazes is inside."""
        small = self._blocks(block)
        h, w = small.median.shape[:2]
        score2 = small._score2(_block_means(image, block, (w, h)), inverse_gain, (slice(0, h), slice(0, w)))
        hit = (score2 > np.float32((threshold * BLOCK_SHARE) ** 2)).astype(np.uint8)
        hit = cv2.dilate(hit, np.ones((3, 3), np.uint8))
        # each blob's box from its outer contour (a blob inside another's hole is inside its box):
        # a fifteenth of labelling the blocks
        contours = cv2.findContours(hit, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)[0]
        if not contours:
            return []
        x, y, bw, bh = np.array([cv2.boundingRect(c) for c in contours]).T
        if len(contours) > MAX_WINDOWS:
            x, y, bw, bh = ([v] for v in (x.min(), y.min(), (x + bw).max() - x.min(), (y + bh).max() - y.min()))
        sy, sx = self.shape[0] / h, self.shape[1] / w
        return [(slice(int(y0 * sy), min(int(np.ceil((y0 + hh) * sy)), self.shape[0])),
                 slice(int(x0 * sx), min(int(np.ceil((x0 + ww) * sx)), self.shape[1])))
                for x0, y0, ww, hh in zip(x, y, bw, bh)]

    def _blocks(self, block: int) -> "BackgroundModel":
        """This background in blocks of `block` px (cached): mean colour and mean noise."""
        cache = self.__dict__.setdefault("_block_cache", {})
        if block not in cache:
            size = (self.shape[1] // block, self.shape[0] // block)
            cache[block] = BackgroundModel(cv2.resize(self.median, size, interpolation=cv2.INTER_AREA),
                                           cv2.resize(self.sigma, size, interpolation=cv2.INTER_AREA))
        return cache[block]


@jit
def _score2_kernel(image: np.ndarray, median: np.ndarray, sigma: np.ndarray, inverse_gain: np.float32,
                   tolerance: np.float32) -> np.ndarray:
    """Each pixel's squared colour difference to the background in noise sigmas, the mean over its
    channels: ((image * inverse_gain - median) ** 2 / (sigma ** 2 + (tolerance * median) ** 2)).
    One pass without temporaries: the same in numpy made nine passes over a window's floats and
    was half of the foreground's time."""
    h, w = sigma.shape
    out = np.empty((h, w), np.float32)
    third = np.float32(1 / 3)
    for y in range(h):
        for x in range(w):
            noise2 = sigma[y, x] * sigma[y, x]
            total = np.float32(0)
            for c in range(3):
                m = median[y, x, c]
                d = np.float32(image[y, x, c]) * inverse_gain - m
                relative = tolerance * m
                total += d * d / (noise2 + relative * relative)
            out[y, x] = total * third
    return out


@jit
def _fit_kernel(frames: np.ndarray, gains: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """BackgroundModel.fit's median (H,W,3) float32 of the frames (N,H,W,3) divided by their gains
    (N,) and its median absolute deviation (H,W) float32 (times 1.4826, the largest over the
    channels; zero for fewer than 3 frames), each median as np.median gives it. A row at a time,
    sorted by median_of_frames' network over the row's values (its loops run over a row in SIMD):
    as whole-frame passes in numpy, with their temporaries, the four backgrounds of a 1280x720 rig
    took 1.8 s, half of segment's start-up on a 2 s take."""
    n, h, w = frames.shape[:3]
    median = np.empty((h, w, 3), np.float32)
    mad = np.zeros((h, w), np.float32)
    rows = np.empty((n, w * 3), np.float32)
    middle = np.empty(w * 3, np.float32)
    scale, two = np.float32(1.4826), np.float32(2)
    for y in range(h):
        for k in range(n):
            row = frames[k, y].ravel()
            for i in range(w * 3):
                rows[k, i] = np.float32(row[i]) / gains[k]
        # the median of the values, then of their distances to it
        for stage in range(2 if n >= 3 else 1):
            if stage == 1:
                for k in range(n):
                    for i in range(w * 3):
                        rows[k, i] = abs(rows[k, i] - middle[i])
            for rnd in range(n):
                for k in range(rnd % 2, n - 1, 2):
                    for i in range(w * 3):
                        a, b = rows[k, i], rows[k + 1, i]
                        rows[k, i], rows[k + 1, i] = min(a, b), max(a, b)
            for i in range(w * 3):
                middle[i] = rows[n // 2, i] if n % 2 else (rows[n // 2 - 1, i] + rows[n // 2, i]) / two
            if stage == 0:
                median[y] = middle.reshape(w, 3)
            else:
                for x in range(w):
                    mad[y, x] = max(middle[3 * x], middle[3 * x + 1], middle[3 * x + 2]) * scale
    return median, mad


def median_of_frames(frames: np.ndarray) -> np.ndarray:
    """np.median(frames, axis=0), the same values, for a few frames (N,...): sorted by a network of
    elementwise minima and maxima (odd-even transposition, N rounds). numpy partitions each pixel's
    N values on its own: 0.2 s for 5 frames of 1280x720, against 0.02."""
    n = len(frames)
    if n > 16:
        return np.median(frames, axis=0)
    rows = [np.asarray(f) for f in frames]
    for rnd in range(n):
        for i in range(rnd % 2, n - 1, 2):
            rows[i], rows[i + 1] = np.minimum(rows[i], rows[i + 1]), np.maximum(rows[i], rows[i + 1])
    return rows[n // 2] if n % 2 else (rows[n // 2 - 1] + rows[n // 2]) / 2


def _block_means(image: np.ndarray, block: int, size: tuple[int, int]) -> np.ndarray:
    """The image's means over blocks of `block` px, `size` (w, h). A power of two is halved step by
    step: OpenCV's area resize by 2 twice is 3.5x faster than by 4 once (0.27 against 0.94 ms at
    1280x720). It rounds each step to a grey level: the means are off by up to 1, against a block
    threshold of THRESHOLD_SIGMA * BLOCK_SHARE noise sigmas, 3 grey levels or more."""
    while block > 2 and block % 2 == 0:
        image = cv2.resize(image, (image.shape[1] // 2, image.shape[0] // 2), interpolation=cv2.INTER_AREA)
        block //= 2
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def channel_sum(image: np.ndarray) -> np.ndarray:
    """(H,W) float32 sum of an (H,W,3) image's channels (cv2.transform: numpy's sum over a last axis
    of 3 is several times slower)."""
    return cv2.transform(np.ascontiguousarray(image, np.float32), np.ones((1, 3), np.float32))


def bounding_window(mask: np.ndarray, margin: int) -> tuple[slice, slice] | None:
    """(rows, columns) of the mask's bounding box grown by `margin` px (within the image); None for
    an empty mask."""
    rows = np.flatnonzero(mask.any(axis=1))
    if not len(rows):
        return None
    # the columns only over the rows with any (a hand is a few percent of a 1280x720 view)
    cols = np.flatnonzero(mask[rows[0]:rows[-1] + 1].any(axis=0))
    return grow_window((slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)), margin, mask.shape)


def window_box(mask: np.ndarray, window: tuple[slice, slice]) -> tuple[slice, slice] | None:
    """The bounding box (rows, columns of the image) of a mask (h,w) that is the image's `window`;
    None for an empty mask."""
    box = bounding_window(mask, 0)
    return None if box is None else tuple(slice(w.start + b.start, w.start + b.stop) for w, b in zip(window, box))


def grow_window(window: tuple[slice, slice], margin: int, shape: tuple[int, ...]) -> tuple[slice, slice]:
    """A window (rows, columns) grown by `margin` px on every side, within an image of `shape`."""
    rows, cols = window
    return (slice(max(int(rows.start) - margin, 0), min(int(rows.stop) + margin, shape[0])),
            slice(max(int(cols.start) - margin, 0), min(int(cols.stop) + margin, shape[1])))


def _union(windows: list[tuple[slice, slice]]) -> tuple[slice, slice]:
    return (slice(min(r.start for r, _ in windows), max(r.stop for r, _ in windows)),
            slice(min(c.start for _, c in windows), max(c.stop for _, c in windows)))


def _gain_step(image: np.ndarray) -> int:
    return max(1, int(np.sqrt(image.shape[0] * image.shape[1] / GAIN_SAMPLES)))


def _gain(image: np.ndarray, step: int, reference: np.ndarray) -> float:
    """Brightness ratio of `image` to a reference whose channel sums on the grid of every `step`-th
    row and column are `reference`: the median per-pixel ratio over well-exposed pixels, which the
    foreground (a small part of the view) does not move."""
    ratios = _gain_ratios(image, step, reference)
    return float(np.median(ratios)) if len(ratios) >= 100 else 1.0


@jit
def _gain_ratios(image: np.ndarray, step: int, reference: np.ndarray) -> np.ndarray:
    """_gain's ratios (N,) float32 of the image's channel sums to the reference's on its grid, where
    both are well exposed. (A strided copy, OpenCV's channel sum and numpy's masks: two thirds of
    the gain's time.)"""
    out = np.empty(reference.size, np.float32)
    n = 0
    for gy in range(reference.shape[0]):
        for gx in range(reference.shape[1]):
            y, x = gy * step, gx * step
            ref = reference[gy, gx]
            img = np.float32(image[y, x, 0]) + np.float32(image[y, x, 1]) + np.float32(image[y, x, 2])
            if ref > 30 and ref < 700 and img < 750:
                out[n] = img / ref
                n += 1
    return out[:n]


def remove_small(mask: np.ndarray, min_area: int) -> np.ndarray:
    """The mask without its connected components smaller than min_area pixels."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8,
                                                           ltype=_label_type(mask.shape))
    keep = stats[:, cv2.CC_STAT_AREA] >= min_area
    keep[0] = False
    if keep[1:].all():   # nothing to remove (most views): no pass over the labels
        return np.array(mask, bool)
    return keep[labels]


def _label_type(shape: tuple[int, ...]) -> int:
    """OpenCV's labels of connected components as 16-bit where an image of this shape cannot have
    more than 65,535 of them (8-connected, at most one in each 2x2 block): three times faster than
    32-bit labels on the windows of a 1280x720 view (0.10 against 0.30 ms)."""
    return cv2.CV_16U if (shape[0] + 1) // 2 * ((shape[1] + 1) // 2) < 65_535 else cv2.CV_32S


def fill_holes(mask: np.ndarray, max_area: int | None = None) -> np.ndarray:
    """The mask with its enclosed holes (up to max_area pixels) filled."""
    if max_area is None:
        # every hole: what a flood of the background from a border around the mask does not
        # reach (0.15 ms on a hand's window at 1280x720, where labelling the background took 1.3)
        h, w = mask.shape
        outside = np.zeros((h + 2, w + 2), np.uint8)
        outside[1:-1, 1:-1] = mask
        cv2.floodFill(outside, None, (0, 0), 2, flags=4)
        return outside[1:-1, 1:-1] != 2
    inverse = (~mask).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(inverse, connectivity=4)
    h, w = mask.shape
    x, y, bw, bh = (stats[:, i] for i in range(4))
    touches = (x == 0) | (y == 0) | (x + bw == w) | (y + bh == h)
    hole = ~touches
    if max_area is not None:
        hole &= stats[:, cv2.CC_STAT_AREA] <= max_area
    hole[0] = False
    return mask | hole[labels]
