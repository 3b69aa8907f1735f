"""TAKE/frames.csv: one row per frame the host received (DESIGN.md, "On disk").

    cam,seq,t_device_ns,t_host_ns,bytes,flags

A camera's rows are in the order its packets were written to cams/CAM.mkv: row k of a camera is
its frame index k. The recorder writes the file with `HEADER` and `format_row`; everything else
reads it with `read_frames_csv` (through manus_core.take.Take). Every error names the file and
the line (TakeError, exit code 2 in the CLI).
"""

from __future__ import annotations

import csv
import hashlib
from pathlib import Path

import numpy as np

from manus_core.errors import TakeError

FILE_NAME = "frames.csv"
COLUMNS = ("cam", "seq", "t_device_ns", "t_host_ns", "bytes", "flags")
INT_COLUMNS = ("seq", "t_device_ns", "t_host_ns", "bytes")
HEADER = ",".join(COLUMNS)
FLAG_HOST_JPEG = 1  # flags bit: the host encoded a raw frame to JPEG


def format_row(cam: str, seq: int, t_device_ns: int, t_host_ns: int, n_bytes: int, flags: int | str) -> str:
    """One line of frames.csv, newline included, columns in the order of `COLUMNS`."""
    return f"{cam},{seq},{t_device_ns},{t_host_ns},{n_bytes},{flags}\n"


def read_frames_csv(path: str | Path) -> dict[str, np.ndarray]:
    """The file as columns: cam and flags (str), seq, t_device_ns, t_host_ns, bytes (int64).

    Columns are found by the header, so extra columns are kept (as str) and their order is free."""
    path = Path(path)
    try:
        with open(path, newline="") as f:
            rows = list(csv.reader(f))
    except FileNotFoundError:
        raise TakeError(f"{path}: missing") from None
    if not rows:
        raise TakeError(f"{path}: empty (no header)")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in COLUMNS if c not in header]
    if missing:
        raise TakeError(f"{path}: missing column(s) {', '.join(missing)} (header: {','.join(header)})")
    body = rows[1:]
    short = next((i for i, r in enumerate(body) if len(r) != len(header)), None)
    if short is not None:
        raise TakeError(f"{path}: line {short + 2} has {len(body[short])} fields, the header {len(header)}")
    table = np.array(body, dtype=str).reshape(len(body), len(header))
    out: dict[str, np.ndarray] = {}
    for name in header:
        column = np.char.strip(table[:, header.index(name)])
        if name in INT_COLUMNS:
            try:
                out[name] = column.astype(np.int64)
            except ValueError:
                bad = next(i for i, v in enumerate(column) if not v.lstrip("-").isdigit())
                raise TakeError(f"{path}: line {bad + 2}: {name} is not an integer "
                                f"({column[bad]!r})") from None
        else:
            out[name] = column
    return out


def frames_csv_digest(path: str | Path) -> str:
    """SHA-256 of the file: what results computed from it (the frame groups) are checked against."""
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except FileNotFoundError:
        raise TakeError(f"{path}: missing") from None
