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

One module per format family (cameras_json, panoptic, colmap_text, opencv_yaml, easymocap,
manus_optim_params, anipose_toml); this one detects the format and dispatches, importing only
the module of the format at hand: COLMAP's brings pycolmap and anipose's scipy's rotations, 0.3 s
of a command's start-up that reads a cameras.json.
"""

from __future__ import annotations

import os
from pathlib import Path

from manus_core.cameras import CameraRig
from manus_core.errors import CalibrationFileError

WRITABLE = ("json", "colmap", "opencv-yaml", "easymocap", "manus")
READABLE = WRITABLE + ("anipose", "caliscope", "panoptic")


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
        from .colmap_text import read_colmap
        return read_colmap(folder, units)
    if fmt == "easymocap":
        from .easymocap import read_easymocap
        return read_easymocap(folder, units)
    if path.is_dir():
        path = path / {"json": "cameras.json", "manus": "optim_params.txt", "caliscope": "camera_array.toml",
                       "anipose": "calibration.toml", "opencv-yaml": "cameras.yml",
                       "panoptic": "calibration.json"}[fmt]
    if not path.is_file():
        raise CalibrationFileError(f"{path}: no such calibration file")
    if fmt in ("json", "panoptic"):
        from .cameras_json import read_json
        return read_json(path)
    if fmt in ("anipose", "caliscope"):
        from .anipose_toml import read_toml
        return read_toml(path, units)
    if fmt == "opencv-yaml":
        from .opencv_yaml import read_opencv_yaml
        return read_opencv_yaml(path, units)
    from .manus_optim_params import read_manus
    return read_manus(path, units)


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
        from .opencv_yaml import write_opencv_yaml
        write_opencv_yaml(rig, path)
    elif format == "manus":
        from .manus_optim_params import write_manus
        write_manus(rig, path, lossy)
    elif format == "colmap":
        from .colmap_text import write_colmap
        write_colmap(rig, path, lossy)
    else:
        from .easymocap import write_easymocap
        write_easymocap(rig, path)
