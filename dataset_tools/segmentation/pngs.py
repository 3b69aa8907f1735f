"""Masks made by another tool: PNG folders FOLDER/CAM/FRAME.png (nonzero = foreground)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from manus_core.errors import SegmentationError


def load_png_masks(folder: str | Path, cameras, frames, shape: tuple[int, int]) -> np.ndarray:
    """Masks (T,C,H,W) bool from FOLDER/CAM/FRAME.png for frame indices (T,C) (-1: none, empty)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SegmentationError(f"{folder}: no such mask folder")
    frames = np.asarray(frames, np.int64)
    out = np.zeros((len(frames), len(cameras)) + tuple(shape), bool)
    for c, cam in enumerate(cameras):
        for t, k in enumerate(frames[:, c]):
            if k < 0:
                continue
            path = folder / str(cam) / f"{k:06d}.png"
            mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if mask is None:
                raise SegmentationError(f"{path}: missing or not an image")
            if mask.shape != tuple(shape):
                raise SegmentationError(f"{path}: size {mask.shape[::-1]}, expected {tuple(shape)[::-1]}")
            out[t, c] = mask > 0
    return out
