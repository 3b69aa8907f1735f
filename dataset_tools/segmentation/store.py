"""Where a take's masks go while they are made: arrays in memory, or an HDF5 file on disk that
the tasks' results are written into as they come, so that segmenting a long take needs the memory
of a few frame groups rather than of the take (53 cameras at 1280x720 are 98 MB of masks a group:
a 10 s take at 120 FPS would be 117 GB)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from manus_core.scratch import ScratchArrays

HAND, OBJECT = "masks/hand", "masks/object"


class MaskStore(ScratchArrays):
    """Hand and object masks (T,C,H,W) bool. `path`: an HDF5 file (created, replaced if there),
    one compressed chunk per view and group; None: numpy arrays. `hand` and `object` index like
    arrays either way."""

    def __init__(self, shape: tuple[int, int, int, int], path: Path | None = None) -> None:
        super().__init__(path)
        self.hand, self.object = (self.array(name, shape, bool, (1, 1, *shape[2:])) for name in (HAND, OBJECT))

    def put(self, start: int, hand: np.ndarray, obj: np.ndarray) -> None:
        """The masks (n,C,H,W) of groups start ... start + n - 1."""
        for array, masks in ((self.hand, hand), (self.object, obj)):
            if isinstance(array, np.ndarray):
                array[start:start + len(masks)] = masks
                continue
            # On disk only the views with a mask are written: a chunk never written reads as False and
            # takes no space (in the file, and in DATASET.h5, which copies the chunks as they are),
            # while compressing an empty view costs as much as a full one (1.4 ms at 1280x720).
            for t, c in zip(*np.nonzero(masks.any(axis=(2, 3)))):
                array[start + t, c] = masks[t, c]
