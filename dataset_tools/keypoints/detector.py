"""The Detector: crops hands out of images, runs a keypoint model in batches, maps keypoints back."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from . import boxes as bx
from .models import NUM_JOINTS, KeypointModel, MediaPipeHand, load_model
from .palm import PalmDetector


class Detector:
    """2D hand keypoints in full-image pixels, MediaPipe joint order, from images and hand boxes.

    All crops of all images in one call go through the network together, `batch_size` at a time.
    Models that want upright hands (MediaPipe) get a first pass on the box, turned to the hand's
    axis when it is known and otherwise tried at `orientations` turns, then `refine` passes on a crop
    turned to the axis that the previous pass found, as MediaPipe's tracker does.
    """

    def __init__(self, model: KeypointModel, batch_size: int = 64, orientations: int = 4,
                 palm: PalmDetector | None = None, palm_tiles: bool = False) -> None:
        self.model = model
        self.batch_size = int(batch_size)
        self.orientations = int(orientations)
        self._palm = palm
        self.palm_tiles = palm_tiles

    @property
    def name(self) -> str:
        return self.model.name

    @property
    def providers(self) -> list[str]:
        return self.model.session.providers

    def detect(self, image: np.ndarray, boxes: np.ndarray, angles: np.ndarray | None = None) -> np.ndarray:
        """image (H,W,3) BGR uint8, boxes (N,4) x0,y0,x1,y1 -> (N,21,3) [x, y, confidence].

        angles (N,): the hand's axis where known (see boxes.hand_angle; NaN: unknown). Where it is
        unknown, a model that wants upright hands tries `orientations` turns and keeps the one it is
        most confident about. A box with a NaN gives NaN keypoints with confidence 0.
        """
        return self.detect_many([image], [boxes], None if angles is None else [angles])[0]

    def detect_many(self, images: Sequence[np.ndarray], boxes: Sequence[np.ndarray],
                    angles: Sequence[np.ndarray] | None = None) -> list[np.ndarray]:
        """Batched over views or frames: images[i] with boxes[i] (N_i,4) -> list of (N_i,21,3)."""
        if len(images) != len(boxes) or angles is not None and len(angles) != len(images):
            raise ValueError(f"{len(images)} images but {len(boxes)} box arrays"
                             + ("" if angles is None else f" and {len(angles)} angle arrays"))
        crop = self.model.crop
        rects = []
        for i, (image, b) in enumerate(zip(images, boxes)):
            _check_image(image)
            rects.append(bx.rects_from_boxes(b, crop.box_scale, crop.width / crop.height,
                                             np.nan if angles is None else angles[i]))
        return self.detect_rects(images, rects)

    def detect_rects(self, images: Sequence[np.ndarray], rects: Sequence[np.ndarray],
                     refine: int | None = None) -> list[np.ndarray]:
        """Like detect_many, from crop rects (N_i,5) [cx, cy, w, h, angle] (see boxes.py).

        A NaN angle means unknown: for a model that wants upright hands the first pass tries the rect
        at `orientations` evenly spaced turns and keeps, per hand, the most confident; other models
        crop it unturned. Then `refine` passes re-crop from the keypoints (default: the model's).
        """
        crop = self.model.crop
        refine = crop.refine if refine is None else refine
        counts = [len(r) for r in rects]
        image_of = np.repeat(np.arange(len(images)), counts)
        current = np.concatenate([np.asarray(r, np.float64).reshape(-1, 5) for r in rects]) \
            if rects else np.zeros((0, 5))
        unknown = np.isnan(current[:, 4])
        current[unknown, 4] = 0.0
        valid = np.flatnonzero(np.isfinite(current).all(axis=1) & (current[:, 2] > 0) & (current[:, 3] > 0))
        keypoints = np.full((len(current), NUM_JOINTS, 3), np.nan)
        keypoints[..., 2] = 0.0

        turns = np.where(unknown[valid] & crop.rotate, max(self.orientations, 1), 1)
        owner = np.repeat(np.arange(len(valid)), turns)
        tried = current[valid][owner]
        first = np.cumsum(turns) - turns           # index of each hand's first try
        tried[:, 4] += (np.arange(len(owner)) - first[owner]) * (2 * np.pi / turns[owner])
        found = self._run(images, image_of[valid][owner], tried)
        # Per hand, the turn with the highest confidence (first turn on ties or NaN).
        conf = np.nan_to_num(found[:, 0, 2], nan=-1.0)
        best = np.lexsort((-conf, owner))[first]
        keypoints[valid] = found[best]
        for _ in range(refine if crop.rotate else 0):
            ok = valid[np.isfinite(keypoints[valid, :, :2]).all(axis=(1, 2))]
            keypoints[ok] = self._run(images, image_of[ok], bx.rects_from_keypoints(keypoints[ok]))
        return np.split(keypoints, np.cumsum(counts)[:-1])

    def find_boxes(self, images: Sequence[np.ndarray], max_hands: int = 1,
                   min_score: float = 0.5) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """Hand boxes (M_i,4) and angles (M_i,) from MediaPipe's palm detector, best first.

        A box is the square that, enlarged by MediaPipe's box scale, is the palm detector's hand
        rect; with its angle, detect_many() crops exactly that rect for the MediaPipe model.
        """
        if self._palm is None:
            self._palm = PalmDetector(device=self.model.session.device, tiles=self.palm_tiles)
        self._palm.min_score = min_score
        boxes, angles = [], []
        for rects, _ in self._palm.detect(list(images), max_hands=max_hands):
            half = rects[:, 2:3] / (2 * MediaPipeHand.BOX_SCALE)
            boxes.append(np.concatenate([rects[:, :2] - half, rects[:, :2] + half], axis=1))
            angles.append(rects[:, 4])
        return boxes, angles

    def find_hands(self, images: Sequence[np.ndarray], max_hands: int = 1,
                   min_score: float = 0.5) -> list[np.ndarray]:
        """Keypoints (M_i,21,3) of the hands the palm detector finds in whole images."""
        boxes, angles = self.find_boxes(images, max_hands, min_score)
        return self.detect_many(images, boxes, angles)

    def _run(self, images: Sequence[np.ndarray], image_of: np.ndarray, rects: np.ndarray) -> np.ndarray:
        crop = self.model.crop
        out = np.empty((len(rects), NUM_JOINTS, 3))
        for start in range(0, len(rects), self.batch_size):
            sl = slice(start, start + self.batch_size)
            crops = []
            for i in np.unique(image_of[sl]):
                mine = np.flatnonzero(image_of[sl] == i) + start
                c, A = bx.crop(images[i], rects[mine], crop.width, crop.height)
                crops.append((mine, c, A))
            order = np.concatenate([m for m, _, _ in crops])
            batch = np.concatenate([c for _, c, _ in crops])
            maps = np.concatenate([A for _, _, A in crops])
            kp = self.model(batch)
            kp[..., :2] = bx.apply_affine(bx.invert_affine(maps), kp[..., :2])
            out[order] = kp
        return out


def _check_image(image: np.ndarray) -> None:
    if not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"images must be (H,W,3) BGR uint8 arrays, got "
                         f"{getattr(image, 'shape', type(image))} {getattr(image, 'dtype', '')}")


def hand_keypoint_detector(name: str | Path = "mediapipe-hand", device: str = "auto",
                           threads: int | None = None, batch_size: int = 64, palm_tiles: bool = False) -> Detector:
    """A Detector for `mediapipe-hand` (full), `mediapipe-hand-lite`, `mediapipe-hand-int8` (after
    `models quantize`), or a SimCC/heatmap spec (.toml).

    device: auto (CUDA when onnxruntime has it, else CPU), cpu or cuda. palm_tiles: the palm
    detector also looks at square tiles of wide frames (palm.PalmDetector).
    """
    return Detector(load_model(name, device=device, threads=threads), batch_size=batch_size, palm_tiles=palm_tiles)
