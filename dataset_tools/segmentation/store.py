"""Where a take's masks go while they are made: arrays in memory, or an HDF5 file on disk that
the tasks' results are written into as they come, so that segmenting a long take needs the memory
of a few frame groups rather than of the take (53 cameras at 1280x720 are 98 MB of masks a group:
a 10 s take at 120 FPS would be 117 GB)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from manus_core.scratch import ScratchArrays

HAND, OBJECT = "masks/hand", "masks/object"
# (rows, columns): a 1280x720 view in 16 tiles; 320x180, the demo's, in one
TILE = (180, 320)


class MaskStore(ScratchArrays):
    """Hand and object masks (T,C,H,W) bool. `path`: an HDF5 file (created, replaced if there),
    compressed in tiles of at most TILE px; None: numpy arrays. `hand` and `object` index like
    arrays either way."""

    def __init__(self, shape: tuple[int, int, int, int], path: Path | None = None) -> None:
        super().__init__(path)
        self.tile = tuple(min(t, s) for t, s in zip(TILE, shape[2:]))
        self.hand, self.object = (self.array(name, shape, bool, (1, 1, *self.tile)) for name in (HAND, OBJECT))

    def put(self, start: int, hand: np.ndarray, obj: np.ndarray) -> None:
        """The masks (n,C,H,W) of groups start ... start + n - 1."""
        for array, masks in ((self.hand, hand), (self.object, obj)):
            if isinstance(array, np.ndarray):
                array[start:start + len(masks)] = masks
                continue
            # On disk only the tiles around a view's mask are written: a tile never written reads as
            # False and takes no space (in the file, and in DATASET.h5, which copies the tiles as they
            # are), while compressing an empty one costs as much as a full one (a whole 1280x720 view
            # 1.4-1.9 ms; a hand's box covers a third of it or less)
            for t, c in zip(*np.nonzero(masks.any(axis=(2, 3)))):
                rows, cols = self._tiles(masks[t, c])
                array[start + t, c, rows, cols] = masks[t, c, rows, cols]

    def _tiles(self, mask: np.ndarray) -> tuple[slice, slice]:
        """The rows and columns of the tiles that hold the (nonempty) mask's bounding box."""
        out = []
        for axis, size in enumerate(self.tile):
            hit = np.flatnonzero(mask.any(axis=1 - axis))
            out.append(slice(hit[0] // size * size, min((hit[-1] // size + 1) * size, mask.shape[axis])))
        return out[0], out[1]
