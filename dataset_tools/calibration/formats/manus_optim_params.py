"""MANUS / BRICS optim_params.txt: one camera per line,

    cam_id width height fx fy cx cy k1 k2 p1 p2 cam_name qvecw qvecx qvecy qvecz tvecx tvecy tvecz

COLMAP's world-to-camera quaternion and translation; the intrinsics are used as OpenCV's (no
half-pixel shift). No skew and no k3: writing a rig that has them needs lossy=True.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from manus_core.cameras import CameraRig
from manus_core.errors import CalibrationFileError
from manus_core.fileio import write_atomic
from manus_core.rotations import matrix_to_quat, quat_to_matrix

from .checks import build, plain_ids, require_representable, unit_scale

COLUMNS = ("cam_id width height fx fy cx cy k1 k2 p1 p2 cam_name "
           "qvecw qvecx qvecy qvecz tvecx tvecy tvecz").split()
NAME_LENGTH = 22  # the MANUS reader loads names as numpy '<U22'


def read_manus(path: Path, units: str | None) -> CameraRig:
    """The cameras of an optim_params.txt; a header line with or without '#' is skipped."""
    scale = unit_scale(units, str(path))
    ids, K, dist, R, t, size = [], [], [], [], [], []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        if len(fields) != len(COLUMNS):
            if not ids and not _is_number(fields[0]):
                continue  # a header line without '#'
            raise CalibrationFileError(f"{path}:{number}: {len(fields)} fields, expected {len(COLUMNS)} "
                                       f"({' '.join(COLUMNS)})")
        try:  # a malformed number or a zero quaternion
            v = {k: (f if k == "cam_name" else float(f)) for k, f in zip(COLUMNS, fields)}
            R.append(quat_to_matrix(np.array([v["qvecw"], v["qvecx"], v["qvecy"], v["qvecz"]])))
        except ValueError as exc:
            raise CalibrationFileError(f"{path}:{number}: {exc}") from None
        ids.append(v["cam_name"])
        K.append([[v["fx"], 0, v["cx"]], [0, v["fy"], v["cy"]], [0, 0, 1]])
        dist.append([v["k1"], v["k2"], v["p1"], v["p2"], 0.0])
        t.append(np.array([v["tvecx"], v["tvecy"], v["tvecz"]]) * scale)
        size.append([v["width"], v["height"]])
    return build(str(path), ids, K, dist, R, t, size)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _num(x: float) -> str:
    """Shortest text that reads back as the same double."""
    return repr(float(x))


def write_manus(rig: CameraRig, path: Path, lossy: bool) -> None:
    """The rig as optim_params.txt (with a '#' header line), written atomically."""
    require_representable(rig, path, "MANUS", lossy, skew=True, k3=True)
    plain_ids(rig, path, "MANUS")
    long = [i for i in rig.ids if len(i) > NAME_LENGTH]
    if long:
        raise CalibrationFileError(f"{path}: MANUS readers keep {NAME_LENGTH} characters of a camera name; "
                                   f"too long: {long}")
    lines = ["# " + " ".join(COLUMNS)]
    for i, cam_id in enumerate(rig.ids):
        K, d = rig.K[i], rig.dist[i]
        values = [str(i), str(int(rig.size[i, 0])), str(int(rig.size[i, 1])),
                  *map(_num, (K[0, 0], K[1, 1], K[0, 2], K[1, 2], d[0], d[1], d[2], d[3])), cam_id,
                  *map(_num, matrix_to_quat(rig.R[i])), *map(_num, rig.t[i])]
        lines.append(" ".join(values))
    write_atomic(path, ("\n".join(lines) + "\n").encode())
