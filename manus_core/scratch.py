"""Arrays a stage fills task by task: in memory, or in an HDF5 file beside its output, so that a
long take needs the memory of a few tasks rather than of the take. The file's datasets are copied
into DATASET.h5 as they are (manus_core.dataset.add_arrays) and the file is removed after."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

GZIP_LEVEL = 1   # of the files' arrays (ScratchArrays.array says why)


class ScratchArrays:
    """Arrays by name: numpy arrays when `path` is None, else gzip datasets of an HDF5 file at
    `path` (created; replaced if there). Index them like arrays either way."""

    def __init__(self, path: Path | None = None) -> None:
        self.path = path
        self._file: h5py.File | None = None
        if path is not None:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            self._file = h5py.File(path, "w")

    def array(self, name: str, shape: tuple[int, ...], dtype, chunks: tuple[int, ...]) -> np.ndarray | h5py.Dataset:
        """A new zeroed array; on disk in `chunks`, compressed at gzip level 1 (the arrays are copied
        into DATASET.h5 chunk by chunk, as they are: level 1 shrinks mostly-empty chunks as much as
        add_arrays' 4, in less time)."""
        if self._file is None:
            return np.zeros(shape, dtype)
        return self._file.create_dataset(name, shape, dtype, chunks=chunks, compression="gzip",
                                         compression_opts=GZIP_LEVEL)

    def close(self, remove: bool = True) -> None:
        """Close the file (and remove it, by default: its arrays have been copied by then)."""
        if self._file is not None:
            self._file.close()
            self._file = None
            if remove and self.path is not None:
                Path(self.path).unlink(missing_ok=True)
