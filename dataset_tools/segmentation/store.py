"""Where a take's masks go while they are made: arrays in memory, or an HDF5 file on disk that
the tasks' results are written into as they come, so that segmenting a long take needs the memory
of a few frame groups rather than of the take (53 cameras at 1280x720 are 98 MB of masks a group:
a 10 s take at 120 FPS would be 117 GB)."""

from __future__ import annotations

import zlib
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from manus_core.scratch import GZIP_LEVEL, ScratchArrays

from .background import bounding_window, window_box

HAND, OBJECT = "masks/hand", "masks/object"
# (rows, columns): a 1280x720 view in 16 tiles; 320x180, the demo's, in one
TILE = (180, 320)


@dataclass(frozen=True)
class ViewMasks:
    """One view's hand and object masks (h,w) bool inside `window` (rows, columns of the image);
    both are empty outside it. `group` counts from the first group of the masks it comes with.
    A task hands its masks over this way: a hand is a small part of a 1280x720 view, and whole
    views were 33 MB of mostly empty arrays a task at four cameras, new memory for every task whose
    pages cost time to touch the first time (about 5 % of segment's time a view, measured)."""

    group: int
    camera: int
    window: tuple[slice, slice]
    hand: np.ndarray
    object: np.ndarray


def views_of(hand: np.ndarray, obj: np.ndarray) -> list[ViewMasks]:
    """The views of whole masks (n,C,H,W) that hold a hand or object pixel, each in its box."""
    either = hand | obj
    return [ViewMasks(int(t), int(c), window, hand[t, c][window], obj[t, c][window])
            for t, c in zip(*np.nonzero(either.any(axis=(2, 3))))
            for window in [bounding_window(either[t, c], 0)]]


class MaskStore(ScratchArrays):
    """Hand and object masks (T,C,H,W) bool. `path`: an HDF5 file (created, replaced if there),
    compressed in tiles of at most TILE px; None: numpy arrays. `hand` and `object` index like
    arrays either way."""

    def __init__(self, shape: tuple[int, int, int, int], path: Path | None = None) -> None:
        super().__init__(path)
        self.tile = tuple(min(t, s) for t, s in zip(TILE, shape[2:]))
        self.hand, self.object = (self.array(name, shape, bool, (1, 1, *self.tile)) for name in (HAND, OBJECT))

    def put(self, start: int, hand: np.ndarray, obj: np.ndarray) -> None:
        """The whole masks (n,C,H,W) of groups start ... start + n - 1."""
        self.put_views(start, views_of(hand, obj))

    def put_views(self, start: int, views: Iterable[ViewMasks]) -> None:
        """The masks of views of groups from `start` on (ViewMasks.group counts from it); a view not
        given stays empty."""
        for view in views:
            for array, masks in ((self.hand, view.hand), (self.object, view.object)):
                if isinstance(array, np.ndarray):
                    array[(start + view.group, view.camera, *view.window)] = masks
                    continue
                # On disk only the tiles around a view's mask are written: a tile never written reads
                # as False and takes no space (in the file, and in DATASET.h5, which copies the tiles
                # as they are), while compressing an empty one costs as much as a full one (a whole
                # 1280x720 view 1.4-1.9 ms; a hand's box covers a third of it or less)
                # the mask's box in the image, and the tiles that hold it
                box = window_box(masks, view.window)
                if box is None:
                    continue
                tiles = tuple(slice(b.start // size * size, min(-(-b.stop // size) * size, length))
                              for b, size, length in zip(box, self.tile, array.shape[2:]))
                block = np.zeros([t.stop - t.start for t in tiles], bool)
                block[tuple(slice(b.start - t.start, b.stop - t.start) for b, t in zip(box, tiles))] = \
                    masks[tuple(slice(b.start - w.start, b.stop - w.start) for b, w in zip(box, view.window))]
                self._write_tiles(array, (start + view.group, view.camera, tiles[0].start, tiles[1].start), block)

    def _write_tiles(self, array, corner: tuple[int, int, int, int], block: np.ndarray) -> None:
        """The tiles of `block` (whole tiles from `corner` (group, camera, row, column) on, the last
        ones cut at the image's edge) that hold a mask pixel, each compressed here as the dataset's
        gzip filter would and written as its chunk: through HDF5's filter pipeline, a view's few
        tiles cost as much again as compressing them."""
        th, tw = self.tile
        t, c, top, left = corner
        for y in range(0, block.shape[0], th):
            for x in range(0, block.shape[1], tw):
                tile = block[y:y + th, x:x + tw]
                if not tile.any():
                    continue
                chunk = np.zeros(self.tile, bool)   # a chunk is whole, past the image's edge too
                chunk[:tile.shape[0], :tile.shape[1]] = tile
                array.id.write_direct_chunk((t, c, top + y, left + x), zlib.compress(chunk, GZIP_LEVEL))
