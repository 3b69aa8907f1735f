"""Where a take's masks go while they are made: arrays in memory, or an HDF5 file on disk that
the tasks' results are written into as they come, so that segmenting a long take needs the memory
of a few frame groups rather than of the take (53 cameras at 1280x720 are 98 MB of masks a group:
a 10 s take at 120 FPS would be 117 GB)."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

HAND, OBJECT = "masks/hand", "masks/object"


class MaskStore:
    """Hand and object masks (T,C,H,W) bool. `path`: an HDF5 file (created, replaced if there),
    one compressed chunk per view and group; None: numpy arrays. `hand` and `object` index like
    arrays either way."""

    def __init__(self, shape: tuple[int, int, int, int], path: Path | None = None) -> None:
        self.path = path
        self._file: h5py.File | None = None
        if path is None:
            self.hand, self.object = np.zeros(shape, bool), np.zeros(shape, bool)
            return
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        self._file = h5py.File(path, "w")
        # gzip, which every HDF5 reader has (the chunks are copied into DATASET.h5 as they are);
        # level 1: mostly-empty masks shrink as much as at add_arrays' 4, in less time
        self.hand, self.object = (self._file.create_dataset(name, shape, bool, chunks=(1, 1, *shape[2:]),
                                                            compression="gzip", compression_opts=1)
                                  for name in (HAND, OBJECT))

    def put(self, start: int, hand: np.ndarray, obj: np.ndarray) -> None:
        """The masks (n,C,H,W) of groups start ... start + n - 1."""
        self.hand[start:start + len(hand)] = hand
        self.object[start:start + len(obj)] = obj

    def close(self, remove: bool = True) -> None:
        """Close the file (and remove it, by default: its masks have been copied by then)."""
        if self._file is not None:
            self._file.close()
            self._file = None
            if remove and self.path is not None:
                Path(self.path).unlink(missing_ok=True)
