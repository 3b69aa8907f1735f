"""EasyMocap calibrations: intri.yml (names, K_<name>, dist_<name>) beside extri.yml (R_<name>
Rodrigues, Rot_<name> matrix, T_<name>), in metres.

EasyMocap keeps no image size: W_/H_ are written by this project and read back (0 = unknown).
Names go into FileStorage keys, so ids are written key-safe with the original ids beside them.
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2

from manus_core.cameras import CameraRig
from manus_core.errors import CalibrationFileError
from manus_core.fileio import write_atomic
from manus_core.rotations import matrix_to_rotvec, rotvec_to_matrix

from .checks import build, dist5, unit_scale
from .filestorage import fs_dist, fs_mat, fs_open, fs_strings, fs_writer

_IDS_KEY = "manus_capture_ids"  # the ids as they were, beside the key-safe names


def _key_name(cam_id: str) -> str:
    """A name usable in FileStorage keys (letters, digits, '_', '-'): others become _<hex>, so
    'x+00' is written as 'x_2b00'."""
    return re.sub(r"[^A-Za-z0-9_-]", lambda m: f"_{ord(m.group()):02x}", cam_id)


def read_easymocap(folder: Path, units: str | None) -> CameraRig:
    """The cameras of folder/intri.yml and folder/extri.yml."""
    intri_path, extri_path = folder / "intri.yml", folder / "extri.yml"
    for p in (intri_path, extri_path):
        if not p.is_file():
            raise CalibrationFileError(f"{p}: missing; EasyMocap calibrations are intri.yml and extri.yml side by side")
    intri, extri = fs_open(intri_path), fs_open(extri_path)
    names = fs_strings(intri.getNode("names"))
    if not names:
        raise CalibrationFileError(f"{intri_path}: has no 'names' list")
    scale = unit_scale(units, str(extri_path))
    ids = fs_strings(intri.getNode(_IDS_KEY))
    if len(ids) != len(names):
        ids = names
    K, dist, R, t, size = [], [], [], [], []
    for name in names:
        K.append(fs_mat(intri.getNode(f"K_{name}"), str(intri_path), f"K_{name}", (3, 3)))
        dist.append(dist5(fs_dist(intri.getNode(f"dist_{name}")), str(intri_path), name))
        rot = extri.getNode(f"Rot_{name}")
        if not rot.empty():
            R.append(fs_mat(rot, str(extri_path), f"Rot_{name}", (3, 3)))
        else:
            R.append(rotvec_to_matrix(fs_mat(extri.getNode(f"R_{name}"), str(extri_path), f"R_{name}", (3,))))
        t.append(fs_mat(extri.getNode(f"T_{name}"), str(extri_path), f"T_{name}", (3,)) * scale)
        w, h = intri.getNode(f"W_{name}"), intri.getNode(f"H_{name}")
        size.append([w.real() if not w.empty() else 0, h.real() if not h.empty() else 0])
    return build(str(folder), ids, K, dist, R, t, size)


def write_easymocap(rig: CameraRig, folder: Path) -> None:
    """intri.yml and extri.yml into `folder`, each written atomically."""
    names = [_key_name(i) for i in rig.ids]
    if len(set(names)) != len(names):
        raise CalibrationFileError(f"{folder}: camera ids {list(rig.ids)} do not give distinct EasyMocap names")
    intri, extri = fs_writer(), fs_writer()
    for fs, key, values in ((intri, "names", names), (extri, "names", names), (intri, _IDS_KEY, rig.ids)):
        fs.startWriteStruct(key, cv2.FileNode_SEQ)
        for value in values:
            fs.write("", value)
        fs.endWriteStruct()
    for i, cam_id in enumerate(names):
        intri.write(f"K_{cam_id}", rig.K[i])
        intri.write(f"dist_{cam_id}", rig.dist[i].reshape(1, 5))
        intri.write(f"W_{cam_id}", int(rig.size[i, 0]))
        intri.write(f"H_{cam_id}", int(rig.size[i, 1]))
        extri.write(f"R_{cam_id}", matrix_to_rotvec(rig.R[i]).reshape(3, 1))
        extri.write(f"Rot_{cam_id}", rig.R[i])
        extri.write(f"T_{cam_id}", rig.t[i].reshape(3, 1))
    write_atomic(folder / "intri.yml", intri.releaseAndGetString().encode())
    write_atomic(folder / "extri.yml", extri.releaseAndGetString().encode())
