"""Colour cues that do not change with the LED level: chromaticity histograms and paint keys.

Chromaticity (b, g, r) / (b + g + r) is unchanged when the lights scale a frame, so a colour
learnt in one take holds in the next. Mixed pixels on an edge lie on the line between the two
colours, so a paint pixel is found by unmixing along the skin-to-paint line: a pixel is paint
when more than half of it is (which is how per-pixel truth that takes the majority is defined).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from manus_core.errors import SegmentationError

BINS = 48


def chromaticity(image: np.ndarray) -> np.ndarray:
    """(..., 2) the (g, r) shares of (b + g + r) of BGR pixels (..., 3); b is 1 - g - r."""
    image = np.asarray(image, np.float32)
    total = image.sum(axis=-1, keepdims=True) + 1e-3
    return image[..., 1:] / total


@dataclass(frozen=True)
class ColourModel:
    """A normalised, smoothed chromaticity histogram of one class of pixels (an object, skin)."""

    density: np.ndarray    # (BINS, BINS) summing to 1
    threshold: float       # density above which a pixel is taken for this class

    @classmethod
    def fit(cls, pixels: np.ndarray, coverage: float = 0.98) -> "ColourModel":
        """From BGR pixels (N,3); `threshold` keeps `coverage` of the training pixels."""
        pixels = np.asarray(pixels, np.float32).reshape(-1, 3)
        if len(pixels) < 20:
            raise SegmentationError(f"colour model: only {len(pixels)} pixels to learn from (need 20)")
        density = _histogram(chromaticity(pixels))
        values = np.sort(density[_bins(chromaticity(pixels))])
        return cls(density, float(values[int((1 - coverage) * (len(values) - 1))]))

    def likelihood(self, image: np.ndarray) -> np.ndarray:
        return self.density[_bins(chromaticity(image))]

    def matches(self, image: np.ndarray) -> np.ndarray:
        return self.likelihood(image) >= self.threshold


def _bins(chroma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    idx = np.clip((chroma * BINS).astype(np.int64), 0, BINS - 1)
    return idx[..., 0], idx[..., 1]


def _histogram(chroma: np.ndarray) -> np.ndarray:
    hist = np.zeros((BINS, BINS), np.float32)
    np.add.at(hist, _bins(chroma), 1.0)
    hist = cv2.GaussianBlur(hist, (5, 5), 0.8)
    return hist / hist.sum()


@dataclass(frozen=True)
class PaintKey:
    """The paint's chromaticity and how far from it a pixel may lie (estimated or given)."""

    colour: np.ndarray     # (2,) chromaticity of the paint
    spread: float          # radius in chromaticity of the paint's own pixels (shading, noise)

    @classmethod
    def from_pixels(cls, pixels: np.ndarray) -> "PaintKey":
        """From pixels of the painted object (N,3) BGR: their median and 95th-percentile spread.
        Dark pixels say little about colour, so only the brighter half is used."""
        pixels = np.asarray(pixels, np.float32).reshape(-1, 3)
        bright = pixels[pixels.sum(axis=1) >= np.median(pixels.sum(axis=1))]
        if len(bright) < 10:
            raise SegmentationError(f"paint colour: only {len(bright)} usable pixels of the painted object")
        chroma = chromaticity(bright)
        colour = np.median(chroma, axis=0)
        spread = float(np.percentile(np.linalg.norm(chroma - colour, axis=1), 95))
        if np.linalg.norm(colour - 1 / 3) < 0.05:
            raise SegmentationError(f"paint colour: the painted object's pixels are grey (chromaticity "
                                    f"{colour.round(3).tolist()}); no paint colour found")
        return cls(colour, max(spread, 0.01))

    @classmethod
    def from_swatch(cls, bgr, spread: float = 0.03) -> "PaintKey":
        """From a given paint colour (B, G, R in 0..255, e.g. measured on a swatch)."""
        bgr = np.asarray(bgr, np.float32).reshape(3)
        colour = chromaticity(bgr)
        if np.linalg.norm(colour - 1 / 3) < 0.05:
            raise SegmentationError(f"paint swatch {bgr.tolist()}: a grey colour cannot be told from skin and walls")
        return cls(colour, spread)

    def fraction(self, image: np.ndarray, base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per pixel, the share of paint when a pixel mixes the paint with the `base` colour (2,)
        chromaticity (skin), and the distance off the base-to-paint line (both (H,W))."""
        chroma = chromaticity(image)
        axis = self.colour - np.asarray(base, np.float32)
        length = float(np.linalg.norm(axis))
        if length < 1e-6:
            raise SegmentationError("paint colour equals the skin colour: paint cannot be seen")
        rel = chroma - base
        along = rel @ (axis / length)
        off = np.abs(rel @ np.array([-axis[1], axis[0]], np.float32) / length)
        return along / length, off

    def mask(self, image: np.ndarray, base: np.ndarray, region: np.ndarray | None = None) -> np.ndarray:
        """Pixels more than half paint (against `base`), within `region` when given."""
        share, off = self.fraction(image, base)
        out = (share > 0.5) & (off < 2 * self.spread + 0.02)
        return out & region if region is not None else out

    def key(self, image: np.ndarray) -> np.ndarray:
        """Pixels of the paint colour on their own (a chroma key, e.g. a green screen)."""
        return np.linalg.norm(chromaticity(image) - self.colour, axis=-1) <= 2 * self.spread


def dominant_colour_key(image: np.ndarray) -> PaintKey:
    """A chroma key for the most common saturated colour of an image (a green screen behind a
    hand): the peak of its chromaticity histogram, with the spread of the pixels near the peak."""
    chroma = chromaticity(image).reshape(-1, 2)
    saturated = np.linalg.norm(chroma - 1 / 3, axis=1) > 0.05
    if np.count_nonzero(saturated) < 100:
        raise SegmentationError("chroma key: the image has no saturated colour to key on")
    hist = _histogram(chroma[saturated])
    peak = np.array(np.unravel_index(np.argmax(hist), hist.shape), np.float32)
    colour = (peak + 0.5) / BINS
    near = chroma[np.linalg.norm(chroma - colour, axis=1) < 0.1]
    colour = np.median(near, axis=0)
    spread = float(np.percentile(np.linalg.norm(near - colour, axis=1), 90))
    return PaintKey(colour, max(spread, 0.01))
