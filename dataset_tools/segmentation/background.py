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

# The MAD of a few JPEG frames underestimates the noise of a new frame: a floor in grey levels.
NOISE_FLOOR = 2.5
# Colour differences this many noise sigmas above the background count as foreground.
THRESHOLD_SIGMA = 3.0
# Shading of the background changes by a few percent with the LED level (JPEG, clipping):
# a relative tolerance keeps bright walls from turning into foreground.
RELATIVE_TOLERANCE = 0.03
# The gain is the median ratio over a regular grid of about this many pixels: at 1280x720 every
# 4th row and column, which gives the whole frame's median to ~1e-3 at a sixteenth of the cost
# (320x180 is sampled whole).
GAIN_SAMPLES = 50_000


@dataclass(frozen=True)
class BackgroundModel:
    """One camera's background: median image (H,W,3) float32 and noise sigma (H,W) float32."""

    median: np.ndarray
    sigma: np.ndarray

    @classmethod
    def fit(cls, frames: np.ndarray) -> "BackgroundModel":
        """Fit from frames (N,H,W,3) (uint8 or float 0..255) of one camera, gain-normalised first."""
        frames = np.asarray(frames, np.float32)
        if frames.ndim != 4 or frames.shape[-1] != 3 or len(frames) == 0:
            raise SegmentationError(f"background: expected frames (N,H,W,3), got shape {frames.shape}")
        first = np.median(frames, axis=0)
        gains = np.array([estimate_gain(f, first) for f in frames], np.float32)
        normalised = frames / gains[:, None, None, None]
        median = np.median(normalised, axis=0)
        if len(frames) >= 3:
            mad = np.median(np.abs(normalised - median), axis=0).max(axis=-1) * 1.4826
        else:
            mad = np.zeros(median.shape[:2], np.float32)
        return cls(median.astype(np.float32), np.maximum(mad, NOISE_FLOOR).astype(np.float32))

    @property
    def shape(self) -> tuple[int, int]:
        return self.median.shape[:2]

    def at_brightness(self, image: np.ndarray, window: tuple[slice, slice] | None = None) -> np.ndarray:
        """The background's colours (H,W,3) float32 at the brightness (LED level) of `image`; only
        those of `window` (rows, columns) when given: the gain is still the whole image's."""
        median = self.median if window is None else self.median[window]
        return median * np.float32(estimate_gain(image, self.median))

    def difference(self, image: np.ndarray) -> np.ndarray:
        """Per-pixel colour difference (H,W) to the background in noise sigmas, after the gain."""
        if image.shape != self.median.shape:
            raise SegmentationError(f"image of shape {image.shape} against a background of shape {self.median.shape}")
        diff = np.asarray(image, np.float32) * np.float32(1 / estimate_gain(image, self.median)) - self.median
        scale2 = self.sigma[..., None] ** 2 + (RELATIVE_TOLERANCE * self.median) ** 2
        return np.sqrt((diff * diff / scale2).sum(axis=-1) / np.float32(3))

    def foreground(self, image: np.ndarray, threshold: float = THRESHOLD_SIGMA, min_area: int = 0) -> np.ndarray:
        """Boolean foreground mask (H,W): different from the background, small specks removed."""
        diff = self.difference(image)
        # a 3x3 median of the score (not of the mask) keeps thin fingers but drops single-pixel noise
        mask = cv2.medianBlur(diff.astype(np.float32), 3) > threshold
        return remove_small(mask, min_area) if min_area else mask


def estimate_gain(image: np.ndarray, reference: np.ndarray) -> float:
    """Brightness ratio image/reference: the median per-pixel ratio over well-exposed pixels,
    which the foreground (a small part of the view) does not move."""
    step = max(1, int(np.sqrt(image.shape[0] * image.shape[1] / GAIN_SAMPLES)))
    ref = np.asarray(reference[::step, ::step], np.float32).sum(axis=-1)
    img = np.asarray(image[::step, ::step], np.float32).sum(axis=-1)
    ok = (ref > 30) & (ref < 700) & (img < 750)
    if np.count_nonzero(ok) < 100:
        return 1.0
    return float(np.median(img[ok] / ref[ok]))


def remove_small(mask: np.ndarray, min_area: int) -> np.ndarray:
    """The mask without its connected components smaller than min_area pixels."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= min_area
    keep[0] = False
    return keep[labels]


def fill_holes(mask: np.ndarray, max_area: int | None = None) -> np.ndarray:
    """The mask with its enclosed holes (up to max_area pixels) filled."""
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
