"""Camera calibration files in and out: one CameraRig, many formats.

    rig = load_cameras(path)                    # the format is detected from the path and contents
    save_cameras(rig, out, "colmap")            # json | colmap | opencv-yaml | easymocap | manus

Readable: cameras.json (this project), COLMAP text model (cameras.txt + images.txt, with the
rigs.txt/frames.txt of COLMAP 3.12 / pycolmap 4 when present), OpenCV FileStorage YAML/XML (this
project's multi-camera layout, or the single-camera file of OpenCV's calibration sample),
EasyMocap intri.yml + extri.yml, MANUS/BRICS optim_params.txt, anipose calibration.toml,
caliscope camera_array.toml (and its older config.toml) and the CMU Panoptic calibration JSON.
Writable: the first five. docs/formats.md describes every layout and its conventions.

Everything comes back in this project's conventions: OpenCV pinhole with (k1, k2, p1, p2, k3),
x_cam = R @ x_world + t, metres, pixel centres at integer coordinates. Where a format differs,
the conversion happens here: COLMAP's pixel origin is the corner of the first pixel (cx, cy move
by 0.5 px), CMU Panoptic stores centimetres, anipose stores Rodrigues vectors in board units.

A file that cannot be read raises CalibrationFileError (exit code 2) naming the file and what is
wrong with it. A format that cannot hold part of a rig (skew in COLMAP and MANUS, k3 in MANUS)
refuses to write it unless lossy=True, so a round trip never changes a camera silently.
"""

from __future__ import annotations

import json
import os
import re
import tomllib
from pathlib import Path

import numpy as np

from manus_core.cameras import CalibrationFileError, CameraRig
from manus_core.fileio import write_atomic

WRITABLE = ("json", "colmap", "opencv-yaml", "easymocap", "manus")
READABLE = WRITABLE + ("anipose", "caliscope", "panoptic")
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}

_MANUS_COLUMNS = ("cam_id width height fx fy cx cy k1 k2 p1 p2 cam_name "
                  "qvecw qvecx qvecy qvecz tvecx tvecy tvecz").split()
_MANUS_NAME_LENGTH = 22  # the MANUS reader loads names as numpy '<U22'
_OPENCV_YAML_TAG = "manus-capture cameras"


# ---------------------------------------------------------------------------------------------
# rotations

def _quat_to_matrix(q) -> np.ndarray:
    """Unit quaternion (w, x, y, z), as COLMAP and MANUS write it, to a rotation matrix."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(np.asarray(q, dtype=np.float64), scalar_first=True).as_matrix()


def _matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrix to (w, x, y, z) with w >= 0."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_quat(canonical=True, scalar_first=True)


def _rodrigues(rvec) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))[0]


def _rotation(value, source: str, what: str) -> np.ndarray:
    """A 3x3 matrix or a Rodrigues 3-vector (anipose, EasyMocap) to a rotation matrix."""
    a = np.asarray(value, dtype=np.float64)
    if a.size == 3:
        return _rodrigues(a)
    if a.size == 9:
        return a.reshape(3, 3)
    raise CalibrationFileError(f"{source}: {what} has {a.size} numbers; expected a 3x3 matrix or a Rodrigues 3-vector")


# ---------------------------------------------------------------------------------------------
# checks shared by every reader

def _build(source: str, ids, K, dist, R, t, size, rms=None) -> CameraRig:
    if not len(ids):
        raise CalibrationFileError(f"{source}: holds no cameras")
    try:
        rig = CameraRig(tuple(ids), K, dist, R, t, size, rms)
    except ValueError as exc:
        raise CalibrationFileError(f"{source}: {exc}") from None
    for name in ("K", "dist", "R", "t", "size"):
        bad = ~np.isfinite(getattr(rig, name)).reshape(len(rig), -1).all(axis=1)
        if bad.any():
            raise CalibrationFileError(f"{source}: camera {rig.ids[int(np.argmax(bad))]!r} has a non-finite {name}")
    ortho = np.abs(np.einsum("cji,cjk->cik", rig.R, rig.R) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(rig.R)
    bad = (ortho > 1e-6) | (det < 0)
    if bad.any():
        i = int(np.argmax(bad))
        raise CalibrationFileError(f"{source}: camera {rig.ids[i]!r} has a rotation that is not a rotation "
                                   f"(|R'R - I| = {ortho[i]:.2g}, det = {det[i]:.3f})")
    bad = (rig.K[:, 0, 0] <= 0) | (rig.K[:, 1, 1] <= 0) | (np.abs(rig.K[:, 2] - [0, 0, 1]).max(axis=1) > 0)
    if bad.any():
        raise CalibrationFileError(f"{source}: camera {rig.ids[int(np.argmax(bad))]!r} has an invalid camera "
                                   "matrix (focal lengths must be > 0 and the last row [0, 0, 1])")
    return rig


def _dist5(values, source: str, cam: str) -> list[float]:
    d = [float(v) for v in np.asarray(values, dtype=np.float64).ravel()]
    if any(v != 0 for v in d[5:]):
        raise CalibrationFileError(f"{source}: camera {cam!r} has {len(d)} distortion coefficients; only the "
                                   "5-coefficient OpenCV model (k1, k2, p1, p2, k3) is supported")
    return (d + [0.0] * 5)[:5]


def _unit_scale(units: str | None, source: str) -> float:
    units = "m" if units is None else units
    if units not in UNITS:
        raise CalibrationFileError(f"{source}: unknown length unit {units!r}; use one of {', '.join(UNITS)}")
    return UNITS[units]


def _num(x: float) -> str:
    """Shortest text that reads back as the same double."""
    return repr(float(x))


def _require_representable(rig: CameraRig, path: Path, fmt: str, lossy: bool, skew: bool, k3: bool) -> None:
    if lossy:
        return
    if skew and np.any(rig.K[:, 0, 1] != 0):
        i = int(np.argmax(rig.K[:, 0, 1] != 0))
        raise CalibrationFileError(f"{path}: the {fmt} format has no skew but camera {rig.ids[i]!r} has "
                                   f"skew {float(rig.K[i, 0, 1])!r}; pass lossy=True to drop it")
    if k3 and np.any(rig.dist[:, 4] != 0):
        i = int(np.argmax(rig.dist[:, 4] != 0))
        raise CalibrationFileError(f"{path}: the {fmt} format holds k1 k2 p1 p2 only but camera {rig.ids[i]!r} "
                                   f"has k3 = {float(rig.dist[i, 4])!r}; pass lossy=True to drop it")


def _plain_ids(rig: CameraRig, path: Path, fmt: str) -> None:
    bad = [i for i in rig.ids if not i or re.search(r"\s", i)]
    if bad:
        raise CalibrationFileError(f"{path}: the {fmt} format needs camera ids without whitespace, got {bad}")


# ---------------------------------------------------------------------------------------------
# cameras.json

def _read_json(path: Path) -> CameraRig:
    """cameras.json (its unit recorded in "units") or, recognised by its fields, CMU Panoptic."""
    try:
        doc = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CalibrationFileError(f"{path}: not JSON ({exc})") from None
    if isinstance(doc, dict) and ("calibDataSource" in doc or _looks_panoptic(doc)):
        return _panoptic_from(doc, path)
    rig = CameraRig.from_json(doc, str(path))
    scale = _unit_scale(doc.get("units", "m"), str(path))
    return _build(str(path), rig.ids, rig.K, rig.dist, rig.R, rig.t * scale, rig.size, rig.rms_px)


# ---------------------------------------------------------------------------------------------
# CMU Panoptic (calibration_<session>.json): K, distCoef, R, t in centimetres, 'name' ids

def _looks_panoptic(doc) -> bool:
    cams = doc.get("cameras") if isinstance(doc, dict) else None
    return isinstance(cams, list) and bool(cams) and isinstance(cams[0], dict) and "distCoef" in cams[0]


def _panoptic_from(doc: dict, path: Path) -> CameraRig:
    ids, K, dist, R, t, size = [], [], [], [], [], []
    try:
        for cam in doc["cameras"]:
            ids.append(str(cam["name"]))
            K.append(cam["K"])
            dist.append(_dist5(cam["distCoef"], str(path), cam["name"]))
            R.append(cam["R"])
            t.append(np.asarray(cam["t"], dtype=np.float64).reshape(3) * UNITS["cm"])
            size.append(cam["resolution"])
    except (KeyError, TypeError, ValueError) as exc:
        raise CalibrationFileError(f"{path}: not a CMU Panoptic calibration ({exc!r} in camera {len(ids)})") from None
    return _build(str(path), ids, K, dist, R, t, size)


# ---------------------------------------------------------------------------------------------
# anipose calibration.toml and caliscope camera_array.toml / config.toml

def _read_toml(path: Path, units: str | None) -> CameraRig:
    try:
        doc = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise CalibrationFileError(f"{path}: not TOML ({exc})") from None
    if isinstance(doc.get("cameras"), dict):  # caliscope camera_array.toml: [cameras.N]
        tables = [(str(k), v) for k, v in doc["cameras"].items()]
    else:  # anipose calibration.toml and caliscope's older config.toml: [cam_N]
        tables = [(k, v) for k, v in doc.items() if k.startswith("cam_") and isinstance(v, dict)]
    if not tables:
        raise CalibrationFileError(f"{path}: no camera tables ([cam_0] as anipose writes, "
                                   "or [cameras.0] as caliscope does)")
    scale = _unit_scale(units, str(path))
    ids, K, dist, R, t, size, rms = [], [], [], [], [], [], []
    for key, cam in tables:
        if cam.get("ignore", False):  # caliscope's switch for cameras left out of a session
            continue
        cam_id = str(cam.get("name", cam.get("cam_id", key.removeprefix("cam_"))))
        if cam.get("fisheye", False):
            raise CalibrationFileError(f"{path}: camera {cam_id!r} is a fisheye camera; "
                                       "only the pinhole model is supported")
        missing = [f for f in ("matrix", "distortions", "rotation", "translation", "size") if f not in cam]
        if missing:
            raise CalibrationFileError(f"{path}: camera {cam_id!r} has no {', '.join(missing)}"
                                       + (" (not calibrated yet?)" if "rotation" in missing else ""))
        ids.append(cam_id)
        K.append(cam["matrix"])
        dist.append(_dist5(cam["distortions"], str(path), cam_id))
        R.append(_rotation(cam["rotation"], str(path), f"camera {cam_id!r} rotation"))
        t.append(np.asarray(cam["translation"], dtype=np.float64).reshape(-1) * scale)
        size.append(cam["size"])
        rms.append(float(cam["error"]) if "error" in cam else np.nan)
    return _build(str(path), ids, K, dist, R, t, size, rms)


# ---------------------------------------------------------------------------------------------
# OpenCV FileStorage: this project's multi-camera layout, OpenCV's single-camera sample output

def _fs_open(path: Path):
    import cv2

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        reason = str(exc).strip().splitlines()[-1]
        raise CalibrationFileError(f"{path}: not an OpenCV YAML/XML file ({reason})") from None
    if not fs.isOpened():
        raise CalibrationFileError(f"{path}: cannot be opened as an OpenCV YAML/XML file")
    return fs


def _fs_mat(node, source: str, what: str, shape: tuple[int, ...]) -> np.ndarray:
    if node.empty():
        raise CalibrationFileError(f"{source}: {what} is missing")
    m = node.mat()
    if m is None:
        raise CalibrationFileError(f"{source}: {what} is not a matrix")
    if m.size != int(np.prod(shape)):
        raise CalibrationFileError(f"{source}: {what} has {m.size} values, expected {int(np.prod(shape))}")
    return m.astype(np.float64).reshape(shape)


def _fs_strings(node) -> list[str]:
    """A sequence of names; numeric entries come back as their integer text (as EasyMocap reads them)."""
    out = []
    for i in range(node.size()):
        item = node.at(i)
        out.append(item.string() if item.isString() else str(int(item.real())))
    return out


def _read_opencv_yaml(path: Path, units: str | None) -> CameraRig:
    fs = _fs_open(path)
    root = fs.root()
    if not fs.getNode("names").empty() and any(k.startswith("K_") for k in root.keys()):
        return _read_easymocap(path.parent, units)
    src = str(path)
    scale = _unit_scale(fs.getNode("units").string() if fs.getNode("units").isString() else units, src)
    cams = fs.getNode("cameras")
    if cams.isSeq():
        ids, K, dist, R, t, size, rms = [], [], [], [], [], [], []
        for i in range(cams.size()):
            node = cams.at(i)
            cam_id = node.getNode("id").string() if node.getNode("id").isString() else str(i)
            what = f"camera {cam_id!r}"
            ids.append(cam_id)
            K.append(_fs_mat(node.getNode("K"), src, f"{what} K", (3, 3)))
            d = node.getNode("dist")
            dist.append(_dist5(d.mat() if not d.empty() else [], src, cam_id))
            R.append(_fs_mat(node.getNode("R"), src, f"{what} R", (3, 3)))
            t.append(_fs_mat(node.getNode("t"), src, f"{what} t", (3,)) * scale)
            size.append([node.getNode("width").real(), node.getNode("height").real()])
            rms_node = node.getNode("rms_px")
            rms.append(rms_node.real() if rms_node.isReal() or rms_node.isInt() else np.nan)
        return _build(src, ids, K, dist, R, t, size, rms)
    if not fs.getNode("camera_matrix").empty():  # OpenCV's calibration sample: one camera at the origin
        d = fs.getNode("distortion_coefficients")
        err = fs.getNode("avg_reprojection_error")
        return _build(src, [path.stem], [_fs_mat(fs.getNode("camera_matrix"), src, "camera_matrix", (3, 3))],
                      [_dist5(d.mat() if not d.empty() else [], src, path.stem)], [np.eye(3)], [np.zeros(3)],
                      [[fs.getNode("image_width").real(), fs.getNode("image_height").real()]],
                      [err.real() if not err.empty() else np.nan])
    raise CalibrationFileError(f"{path}: an OpenCV file without cameras (expected a 'cameras' sequence, "
                               "'camera_matrix', or EasyMocap's 'names' and 'K_<name>')")


def _fs_writer():
    import cv2

    return cv2.FileStorage(".yml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)


def _write_opencv_yaml(rig: CameraRig, path: Path) -> None:
    import cv2

    fs = _fs_writer()
    fs.write("format", _OPENCV_YAML_TAG)
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


# ---------------------------------------------------------------------------------------------
# EasyMocap: intri.yml (names, K_<name>, dist_<name>) + extri.yml (R_<name> Rodrigues,
# Rot_<name> matrix, T_<name>), metres

_EASYMOCAP_IDS = "manus_capture_ids"  # the ids as they were, beside the key-safe names


def _easymocap_name(cam_id: str) -> str:
    """A name usable in FileStorage keys (letters, digits, '_', '-'): others become _<hex>, so
    'x+00' is written as 'x_2b00'."""
    return re.sub(r"[^A-Za-z0-9_-]", lambda m: f"_{ord(m.group()):02x}", cam_id)


def _read_easymocap(folder: Path, units: str | None) -> CameraRig:
    intri_path, extri_path = folder / "intri.yml", folder / "extri.yml"
    for p in (intri_path, extri_path):
        if not p.is_file():
            raise CalibrationFileError(f"{p}: missing; EasyMocap calibrations are intri.yml and extri.yml side by side")
    intri, extri = _fs_open(intri_path), _fs_open(extri_path)
    names = _fs_strings(intri.getNode("names"))
    if not names:
        raise CalibrationFileError(f"{intri_path}: has no 'names' list")
    scale = _unit_scale(units, str(extri_path))
    ids = _fs_strings(intri.getNode(_EASYMOCAP_IDS))
    if len(ids) != len(names):
        ids = names
    K, dist, R, t, size = [], [], [], [], []
    for name in names:
        K.append(_fs_mat(intri.getNode(f"K_{name}"), str(intri_path), f"K_{name}", (3, 3)))
        d = intri.getNode(f"dist_{name}")
        dist.append(_dist5(d.mat() if not d.empty() else [], str(intri_path), name))
        rot = extri.getNode(f"Rot_{name}")
        if not rot.empty():
            R.append(_fs_mat(rot, str(extri_path), f"Rot_{name}", (3, 3)))
        else:
            R.append(_rodrigues(_fs_mat(extri.getNode(f"R_{name}"), str(extri_path), f"R_{name}", (3,))))
        t.append(_fs_mat(extri.getNode(f"T_{name}"), str(extri_path), f"T_{name}", (3,)) * scale)
        # EasyMocap itself keeps no image size; H_/W_ are written by this project (0 = unknown).
        w, h = intri.getNode(f"W_{name}"), intri.getNode(f"H_{name}")
        size.append([w.real() if not w.empty() else 0, h.real() if not h.empty() else 0])
    return _build(str(folder), ids, K, dist, R, t, size)


def _write_easymocap(rig: CameraRig, folder: Path) -> None:
    import cv2

    names = [_easymocap_name(i) for i in rig.ids]
    if len(set(names)) != len(names):
        raise CalibrationFileError(f"{folder}: camera ids {list(rig.ids)} do not give distinct EasyMocap names")
    intri, extri = _fs_writer(), _fs_writer()
    for fs, key, values in ((intri, "names", names), (extri, "names", names), (intri, _EASYMOCAP_IDS, rig.ids)):
        fs.startWriteStruct(key, cv2.FileNode_SEQ)
        for value in values:
            fs.write("", value)
        fs.endWriteStruct()
    for i, cam_id in enumerate(names):
        intri.write(f"K_{cam_id}", rig.K[i])
        intri.write(f"dist_{cam_id}", rig.dist[i].reshape(1, 5))
        intri.write(f"W_{cam_id}", int(rig.size[i, 0]))
        intri.write(f"H_{cam_id}", int(rig.size[i, 1]))
        extri.write(f"R_{cam_id}", cv2.Rodrigues(rig.R[i])[0])
        extri.write(f"Rot_{cam_id}", rig.R[i])
        extri.write(f"T_{cam_id}", rig.t[i].reshape(3, 1))
    write_atomic(folder / "intri.yml", intri.releaseAndGetString().encode())
    write_atomic(folder / "extri.yml", extri.releaseAndGetString().encode())


# ---------------------------------------------------------------------------------------------
# MANUS / BRICS optim_params.txt: one camera per line,
#   cam_id width height fx fy cx cy k1 k2 p1 p2 cam_name qvecw qvecx qvecy qvecz tvecx tvecy tvecz
# COLMAP's world-to-camera quaternion and translation; intrinsics used as OpenCV's (no 0.5 shift).

def _read_manus(path: Path, units: str | None) -> CameraRig:
    scale = _unit_scale(units, str(path))
    ids, K, dist, R, t, size = [], [], [], [], [], []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        if len(fields) != len(_MANUS_COLUMNS):
            if not ids and not _is_number(fields[0]):
                continue  # a header line without '#'
            raise CalibrationFileError(f"{path}:{number}: {len(fields)} fields, expected {len(_MANUS_COLUMNS)} "
                                       f"({' '.join(_MANUS_COLUMNS)})")
        try:  # a malformed number or a zero quaternion
            v = {k: (f if k == "cam_name" else float(f)) for k, f in zip(_MANUS_COLUMNS, fields)}
            R.append(_quat_to_matrix([v["qvecw"], v["qvecx"], v["qvecy"], v["qvecz"]]))
        except ValueError as exc:
            raise CalibrationFileError(f"{path}:{number}: {exc}") from None
        ids.append(v["cam_name"])
        K.append([[v["fx"], 0, v["cx"]], [0, v["fy"], v["cy"]], [0, 0, 1]])
        dist.append([v["k1"], v["k2"], v["p1"], v["p2"], 0.0])
        t.append(np.array([v["tvecx"], v["tvecy"], v["tvecz"]]) * scale)
        size.append([v["width"], v["height"]])
    return _build(str(path), ids, K, dist, R, t, size)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _write_manus(rig: CameraRig, path: Path, lossy: bool) -> None:
    _require_representable(rig, path, "MANUS", lossy, skew=True, k3=True)
    _plain_ids(rig, path, "MANUS")
    long = [i for i in rig.ids if len(i) > _MANUS_NAME_LENGTH]
    if long:
        raise CalibrationFileError(f"{path}: MANUS readers keep {_MANUS_NAME_LENGTH} characters of a camera name; "
                                   f"too long: {long}")
    lines = ["# " + " ".join(_MANUS_COLUMNS)]
    for i, cam_id in enumerate(rig.ids):
        K, d = rig.K[i], rig.dist[i]
        values = [str(i), str(int(rig.size[i, 0])), str(int(rig.size[i, 1])),
                  *map(_num, (K[0, 0], K[1, 1], K[0, 2], K[1, 2], d[0], d[1], d[2], d[3])), cam_id,
                  *map(_num, _matrix_to_quat(rig.R[i])), *map(_num, rig.t[i])]
        lines.append(" ".join(values))
    write_atomic(path, ("\n".join(lines) + "\n").encode())


# ---------------------------------------------------------------------------------------------
# COLMAP text model

_COLMAP_MODELS = {  # model -> parameter names, in COLMAP's order
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}


def _colmap_lines(path: Path):
    """(line number, fields) of the data lines; images.txt needs its empty lines, so they stay."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise CalibrationFileError(f"{path}: missing from the COLMAP model") from None
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.startswith("#"):
            yield number, line.split()


def _colmap_cameras(path: Path) -> dict[int, tuple]:
    cams = {}
    for number, f in _colmap_lines(path):
        if not f:
            continue
        if len(f) < 4 or f[1] not in _COLMAP_MODELS:
            model = f[1] if len(f) > 1 else "?"
            raise CalibrationFileError(f"{path}:{number}: camera model {model!r} is not supported "
                                       f"(supported: {', '.join(_COLMAP_MODELS)})")
        names = _COLMAP_MODELS[f[1]]
        if len(f) != 4 + len(names):
            raise CalibrationFileError(f"{path}:{number}: {f[1]} takes {len(names)} parameters, got {len(f) - 4}")
        try:
            p = dict(zip(names, map(float, f[4:])))
            cam_id, width, height = int(f[0]), int(f[2]), int(f[3])
        except ValueError as exc:
            raise CalibrationFileError(f"{path}:{number}: {exc}") from None
        if any(p.get(k, 0.0) != 0.0 for k in ("k4", "k5", "k6")):
            raise CalibrationFileError(f"{path}:{number}: FULL_OPENCV with k4..k6 (rational model) is not supported")
        fx, fy = p.get("fx", p.get("f")), p.get("fy", p.get("f"))
        # COLMAP puts the pixel origin at the corner of the first pixel, OpenCV at its centre.
        K = [[fx, 0.0, p["cx"] - 0.5], [0.0, fy, p["cy"] - 0.5], [0.0, 0.0, 1.0]]
        dist = [p.get("k1", 0.0), p.get("k2", 0.0), p.get("p1", 0.0), p.get("p2", 0.0), p.get("k3", 0.0)]
        cams[cam_id] = (K, dist, (width, height))
    return cams


def _colmap_pose(fields, path: Path, number: int, at: int) -> np.ndarray:
    """Quaternion and translation from fields[at:at+7] as a 3x4 [R | t]."""
    q, t = fields[at:at + 4], fields[at + 4:at + 7]
    if len(q) != 4 or len(t) != 3:
        raise CalibrationFileError(f"{path}:{number}: truncated pose")
    try:  # a malformed number or a zero quaternion
        R = _quat_to_matrix([float(v) for v in q])
        return np.concatenate([R, np.array([float(v) for v in t])[:, None]], axis=1)
    except ValueError as exc:
        raise CalibrationFileError(f"{path}:{number}: {exc}") from None


def _compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[R | t] of a after b."""
    return np.concatenate([a[:, :3] @ b[:, :3], (a[:, :3] @ b[:, 3] + a[:, 3])[:, None]], axis=1)


def _colmap_rigs(folder: Path):
    """sensor_from_rig per camera id and cam_from_world per image id from rigs.txt and frames.txt."""
    rigs_path, frames_path = folder / "rigs.txt", folder / "frames.txt"
    sensor_from_rig, rig_of = {}, {}
    for number, f in _colmap_lines(rigs_path):
        if not f:
            continue
        try:
            rig_id, n_sensors, pos = int(f[0]), int(f[1]), 4
            if f[2] == "CAMERA":
                sensor_from_rig[int(f[3])] = np.eye(3, 4)
                rig_of[int(f[3])] = rig_id
            for _ in range(n_sensors - 1):
                kind, sensor, has_pose = f[pos], int(f[pos + 1]), int(f[pos + 2])
                pose = _colmap_pose(f, rigs_path, number, pos + 3) if has_pose else None
                pos += 3 + 7 * has_pose
                if kind == "CAMERA":
                    sensor_from_rig[sensor] = pose
                    rig_of[sensor] = rig_id
        except (ValueError, IndexError):
            raise CalibrationFileError(f"{rigs_path}:{number}: not a rig line "
                                       "(RIG_ID NUM_SENSORS REF_SENSOR_TYPE REF_SENSOR_ID SENSORS[])") from None
    image_pose = {}
    for number, f in _colmap_lines(frames_path):
        if not f:
            continue
        try:
            rig_from_world = _colmap_pose(f, frames_path, number, 2)
            n_data = int(f[9])
            for j in range(n_data):
                kind, sensor, data = f[10 + 3 * j], int(f[11 + 3 * j]), int(f[12 + 3 * j])
                if kind == "CAMERA" and sensor_from_rig.get(sensor) is not None:
                    image_pose[data] = _compose(sensor_from_rig[sensor], rig_from_world)
        except (ValueError, IndexError):
            raise CalibrationFileError(f"{frames_path}:{number}: not a frame line "
                                       "(FRAME_ID RIG_ID QW QX QY QZ TX TY TZ NUM_DATA_IDS DATA_IDS[])") from None
    return sensor_from_rig, rig_of, image_pose


def _read_colmap(folder: Path, units: str | None) -> CameraRig:
    cams = _colmap_cameras(folder / "cameras.txt")
    images_path = folder / "images.txt"
    images = []  # (image id, [R|t], camera id, name, line number)
    lines = iter(_colmap_lines(images_path))
    for number, f in lines:
        if not f:
            continue
        if len(f) < 10:
            raise CalibrationFileError(f"{images_path}:{number}: not an image line "
                                       "(IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME)")
        try:
            image_id, camera_id = int(f[0]), int(f[8])
        except ValueError as exc:
            raise CalibrationFileError(f"{images_path}:{number}: {exc}") from None
        if camera_id not in cams:
            raise CalibrationFileError(f"{images_path}:{number}: camera {camera_id} is not in cameras.txt")
        images.append((image_id, _colmap_pose(f, images_path, number, 1), camera_id, f[9], number))
        next(lines, None)  # the POINTS2D line of this image
    if not images:
        raise CalibrationFileError(f"{images_path}: holds no registered images")
    scale = _unit_scale(units, str(folder))

    sensor_from_rig, rig_of = {}, {}
    if (folder / "rigs.txt").is_file() and (folder / "frames.txt").is_file():
        sensor_from_rig, rig_of, frame_pose = _colmap_rigs(folder)
        for image_id, pose, _, name, number in images:
            if image_id in frame_pose and np.abs(frame_pose[image_id] - pose).max() > 1e-6:
                raise CalibrationFileError(f"{images_path}:{number}: the pose of {name} disagrees with "
                                           "rigs.txt and frames.txt")

    by_camera: dict[int, list] = {}
    for image in images:
        by_camera.setdefault(image[2], []).append(image)
    moving = [c for c, group in by_camera.items()
              if any(np.abs(g[1] - group[0][1]).max() > 1e-9 for g in group[1:])]
    # A camera seen in several frames with different poses belongs to a moving rig: its fixed
    # calibration is then its pose in the rig (the rig's reference camera becomes the world).
    use_rig = bool(moving) and all(sensor_from_rig.get(c) is not None for c in by_camera) \
        and len({rig_of[c] for c in by_camera}) == 1
    if moving and not use_rig:
        group = by_camera[moving[0]]
        raise CalibrationFileError(f"{images_path}: camera {moving[0]} has images with different poses "
                                   f"({group[0][3]}, {group[1][3]}) and no common rig; keep one frame per camera")
    ids, K, dist, R, t, size = [], [], [], [], [], []
    for camera_id in sorted(by_camera):
        group = by_camera[camera_id]
        pose = sensor_from_rig[camera_id] if use_rig else group[0][1]
        folders = {name.rsplit("/", 1)[0] for _, _, _, name, _ in group if "/" in name}
        if len(folders) == 1 and all("/" in g[3] for g in group):
            ids.append(folders.pop())
        elif len(group) == 1:
            ids.append(Path(group[0][3]).stem)
        else:
            ids.append(str(camera_id))
        k, d, wh = cams[camera_id]
        K.append(k)
        dist.append(d)
        R.append(pose[:, :3])
        t.append(pose[:, 3] * scale)
        size.append(wh)
    if len(set(ids)) != len(ids):
        ids = [str(c) for c in sorted(by_camera)]
    return _build(str(folder), ids, K, dist, R, t, size)


def _write_colmap(rig: CameraRig, folder: Path, lossy: bool) -> None:
    _require_representable(rig, folder, "COLMAP", lossy, skew=True, k3=False)
    _plain_ids(rig, folder, "COLMAP")
    cams = ["# Camera list with one line of data per camera:",
            "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]", f"# Number of cameras: {len(rig)}"]
    images = ["# Image list with two lines of data per image:",
              "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
              "#   POINTS2D[] as (X, Y, POINT3D_ID)", f"# Number of images: {len(rig)}, mean observations per image: 0"]
    for i, cam_id in enumerate(rig.ids):
        K, d = rig.K[i], rig.dist[i]
        params = [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5, *d[:4]]
        model = "OPENCV"
        if d[4] != 0:
            model, params = "FULL_OPENCV", params + [d[4], 0.0, 0.0, 0.0]
        cams.append(" ".join([str(i + 1), model, str(int(rig.size[i, 0])), str(int(rig.size[i, 1])),
                              *map(_num, params)]))
        images.append(" ".join([str(i + 1), *map(_num, _matrix_to_quat(rig.R[i])), *map(_num, rig.t[i]),
                                str(i + 1), f"{cam_id}.jpg"]))
        images.append("")
    points = ["# 3D point list with one line of data per point:",
              "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
              "# Number of points: 0, mean track length: 0"]
    for name, lines in (("cameras.txt", cams), ("images.txt", images), ("points3D.txt", points)):
        write_atomic(folder / name, ("\n".join(lines) + "\n").encode())


# ---------------------------------------------------------------------------------------------
# detection and the public functions

def detect_format(path: str | os.PathLike) -> str:
    """The format name of a calibration file or folder (one of READABLE)."""
    path = Path(path)
    if path.is_dir():
        for names, fmt in ((("cameras.txt", "images.txt"), "colmap"), (("intri.yml", "extri.yml"), "easymocap"),
                           (("cameras.json",), "json"), (("optim_params.txt",), "manus"),
                           (("camera_array.toml",), "caliscope"), (("calibration.toml",), "anipose")):
            if all((path / n).is_file() for n in names):
                return fmt
        raise CalibrationFileError(f"{path}: a folder without a calibration (looked for cameras.txt + images.txt, "
                                   "intri.yml + extri.yml, cameras.json, optim_params.txt, camera_array.toml, "
                                   "calibration.toml)")
    if not path.exists():
        raise CalibrationFileError(f"{path}: no such calibration file or folder")
    suffix = path.suffix.lower()
    if suffix == ".json":
        with open(path, "rb") as f:
            head = f.read(4096)
        return "panoptic" if b"calibDataSource" in head or b"distCoef" in head else "json"
    if suffix == ".toml":
        return "caliscope" if path.name == "camera_array.toml" else "anipose"
    if suffix in (".yml", ".yaml", ".xml"):
        return "easymocap" if path.name in ("intri.yml", "extri.yml") else "opencv-yaml"
    if path.name in ("cameras.txt", "images.txt", "points3D.txt", "rigs.txt", "frames.txt"):
        return "colmap"
    if suffix == ".txt":
        return "manus"
    raise CalibrationFileError(f"{path}: unknown calibration format; name it with format= ({', '.join(READABLE)})")


def load_cameras(path: str | os.PathLike, format: str | None = None, *, units: str | None = None) -> CameraRig:
    """Read a calibration in any supported format (detected unless `format` names it).

    units: the length unit of the file's translations for formats that do not record one
    (anipose and caliscope use their board's unit, usually m or mm; COLMAP, EasyMocap and MANUS
    models are metric when the calibration was scaled): "m" (default), "cm" or "mm". CMU Panoptic
    files are centimetres and cameras.json records its unit, so for those it is ignored.
    """
    path = Path(path)
    fmt = format or detect_format(path)
    if fmt not in READABLE:
        raise CalibrationFileError(f"{path}: unknown format {fmt!r}; readable: {', '.join(READABLE)}")
    folder = path if path.is_dir() else path.parent
    if fmt == "colmap":
        return _read_colmap(folder, units)
    if fmt == "easymocap":
        return _read_easymocap(folder, units)
    if path.is_dir():
        path = path / {"json": "cameras.json", "manus": "optim_params.txt", "caliscope": "camera_array.toml",
                       "anipose": "calibration.toml", "opencv-yaml": "cameras.yml",
                       "panoptic": "calibration.json"}[fmt]
    if not path.is_file():
        raise CalibrationFileError(f"{path}: no such calibration file")
    if fmt in ("json", "panoptic"):
        return _read_json(path)
    if fmt in ("anipose", "caliscope"):
        return _read_toml(path, units)
    if fmt == "opencv-yaml":
        return _read_opencv_yaml(path, units)
    return _read_manus(path, units)


def save_cameras(rig: CameraRig, path: str | os.PathLike, format: str = "json", *, lossy: bool = False) -> None:
    """Write `rig` as `format` (one of WRITABLE); every file is written atomically.

    json, opencv-yaml and manus write the file `path`; colmap and easymocap write their files into
    the folder `path` (created if needed). lossy=True lets a format drop what it cannot hold (skew
    for colmap and manus, k3 for manus) instead of refusing.
    """
    path = Path(path)
    if format not in WRITABLE:
        raise CalibrationFileError(f"{path}: cannot write format {format!r}; writable: {', '.join(WRITABLE)}")
    if format == "json":
        rig.save(path)
    elif format == "opencv-yaml":
        _write_opencv_yaml(rig, path)
    elif format == "manus":
        _write_manus(rig, path, lossy)
    elif format == "colmap":
        _write_colmap(rig, path, lossy)
    else:
        _write_easymocap(rig, path)
