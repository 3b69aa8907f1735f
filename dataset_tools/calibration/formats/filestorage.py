"""OpenCV FileStorage (YAML/XML) helpers shared by the OpenCV and EasyMocap camera files."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from manus_core.errors import CalibrationFileError


def fs_open(path: Path) -> cv2.FileStorage:
    """A FileStorage open for reading; CalibrationFileError when the file is not OpenCV YAML/XML."""
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        reason = str(exc).strip().splitlines()[-1]
        raise CalibrationFileError(f"{path}: not an OpenCV YAML/XML file ({reason})") from None
    if not fs.isOpened():
        raise CalibrationFileError(f"{path}: cannot be opened as an OpenCV YAML/XML file")
    return fs


def fs_mat(node: cv2.FileNode, source: str, what: str, shape: tuple[int, ...]) -> np.ndarray:
    """A matrix node as float64 of `shape`; the error names `what` is missing or wrong."""
    if node.empty():
        raise CalibrationFileError(f"{source}: {what} is missing")
    m = node.mat()
    if m is None:
        raise CalibrationFileError(f"{source}: {what} is not a matrix")
    if m.size != int(np.prod(shape)):
        raise CalibrationFileError(f"{source}: {what} has {m.size} values, expected {int(np.prod(shape))}")
    return m.astype(np.float64).reshape(shape)


def fs_dist(node: cv2.FileNode) -> np.ndarray | list:
    """A distortion node's values (none when the node is missing)."""
    return node.mat() if not node.empty() else []


def fs_strings(node: cv2.FileNode) -> list[str]:
    """A sequence of names; numeric entries come back as their integer text (as EasyMocap reads them)."""
    out = []
    for i in range(node.size()):
        item = node.at(i)
        out.append(item.string() if item.isString() else str(int(item.real())))
    return out


def fs_writer() -> cv2.FileStorage:
    """A FileStorage writing YAML to memory (releaseAndGetString), for atomic writes."""
    return cv2.FileStorage(".yml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
