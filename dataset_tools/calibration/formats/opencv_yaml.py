"""OpenCV FileStorage camera files: this project's multi-camera layout (written here) and the
single-camera output of OpenCV's calibration sample. A file with EasyMocap's keys goes to
easymocap.py."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from manus_core.cameras import CameraRig
from manus_core.errors import CalibrationFileError
from manus_core.fileio import write_atomic

from .checks import build, dist5, unit_scale
from .easymocap import read_easymocap
from .filestorage import fs_dist, fs_mat, fs_open, fs_writer

OPENCV_YAML_TAG = "manus-capture cameras"


def read_opencv_yaml(path: Path, units: str | None) -> CameraRig:
    """A 'cameras' sequence (this project), an OpenCV sample file (one camera at the origin), or
    EasyMocap's intri.yml under another name."""
    fs = fs_open(path)
    root = fs.root()
    if not fs.getNode("names").empty() and any(k.startswith("K_") for k in root.keys()):
        return read_easymocap(path.parent, units)
    src = str(path)
    scale = unit_scale(fs.getNode("units").string() if fs.getNode("units").isString() else units, src)
    cams = fs.getNode("cameras")
    if cams.isSeq():
        ids, K, dist, R, t, size, rms = [], [], [], [], [], [], []
        for i in range(cams.size()):
            node = cams.at(i)
            cam_id = node.getNode("id").string() if node.getNode("id").isString() else str(i)
            what = f"camera {cam_id!r}"
            ids.append(cam_id)
            K.append(fs_mat(node.getNode("K"), src, f"{what} K", (3, 3)))
            dist.append(dist5(fs_dist(node.getNode("dist")), src, cam_id))
            R.append(fs_mat(node.getNode("R"), src, f"{what} R", (3, 3)))
            t.append(fs_mat(node.getNode("t"), src, f"{what} t", (3,)) * scale)
            size.append([node.getNode("width").real(), node.getNode("height").real()])
            rms_node = node.getNode("rms_px")
            rms.append(rms_node.real() if rms_node.isReal() or rms_node.isInt() else np.nan)
        return build(src, ids, K, dist, R, t, size, rms)
    if not fs.getNode("camera_matrix").empty():  # OpenCV's calibration sample: one camera at the origin
        err = fs.getNode("avg_reprojection_error")
        return build(src, [path.stem], [fs_mat(fs.getNode("camera_matrix"), src, "camera_matrix", (3, 3))],
                     [dist5(fs_dist(fs.getNode("distortion_coefficients")), src, path.stem)], [np.eye(3)],
                     [np.zeros(3)], [[fs.getNode("image_width").real(), fs.getNode("image_height").real()]],
                     [err.real() if not err.empty() else np.nan])
    raise CalibrationFileError(f"{path}: an OpenCV file without cameras (expected a 'cameras' sequence, "
                               "'camera_matrix', or EasyMocap's 'names' and 'K_<name>')")


def write_opencv_yaml(rig: CameraRig, path: Path) -> None:
    """The rig as a 'cameras' sequence (id, width, height, K, dist, R, t, rms_px), metres."""
    fs = fs_writer()
    fs.write("format", OPENCV_YAML_TAG)
    fs.write("units", "m")
    fs.startWriteStruct("cameras", cv2.FileNode_SEQ)
    for i, cam_id in enumerate(rig.ids):
        fs.startWriteStruct("", cv2.FileNode_MAP)
        fs.write("id", cam_id)
        fs.write("width", int(rig.size[i, 0]))
        fs.write("height", int(rig.size[i, 1]))
        fs.write("K", rig.K[i])
        fs.write("dist", rig.dist[i].reshape(1, 5))
        fs.write("R", rig.R[i])
        fs.write("t", rig.t[i].reshape(3, 1))
        fs.write("rms_px", float(rig.rms_px[i]))
        fs.endWriteStruct()
    fs.endWriteStruct()
    write_atomic(path, fs.releaseAndGetString().encode())
