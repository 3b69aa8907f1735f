"""Disk space of a take: refusing one that does not fit, and the reserve that lets a take on a
disk that fills up anyway finish its files."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from manus_core.errors import DiskSpaceError
from manus_core.rig_config import RigConfig

BALLAST_BYTES = 32 * 2**20    # reserved at the start, released to finish the take on a full disk
RESERVE_NAME = ".reserve"     # the reserve's file in the take folder
JPEG_BYTES_BASE = 2000        # estimate of a JPEG frame: header + entropy-coded pixels
# q90 of the simulated cube at 720p measures 0.22 B/px with colour at full resolution (4:2:0: 0.17);
# the estimate errs on the safe side
JPEG_BYTES_PER_PIXEL = 0.25


def reserve(path: Path, size: int) -> None:
    """Allocate `size` bytes that the take gives back to finish its files on a full disk."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o600)
    try:
        os.posix_fallocate(fd, 0, size)
    except OSError as exc:
        os.close(fd)
        path.unlink()
        raise DiskSpaceError(f"{path.parent}: cannot reserve {size / 2**20:.0f} MB to finish the take "
                             f"({exc.strerror})") from None
    os.close(fd)


def estimate_take_bytes(rig: RigConfig, duration_s: float) -> int:
    """Bytes a take will need: frames x (JPEG estimate + mkv and frames.csv overhead) per camera."""
    total = 0.0
    for c in rig.cameras:
        frames = c.fps * duration_s + 2
        total += frames * (JPEG_BYTES_BASE + JPEG_BYTES_PER_PIXEL * c.width * c.height + 100)
    return int(total)


def free_bytes(folder: Path) -> int:
    """Free space on the disk that holds `folder` (or would, once created)."""
    probe = folder
    while not probe.exists():
        probe = probe.parent
    return shutil.disk_usage(probe).free


def check_disk(rig: RigConfig, folder: Path, duration_s: float) -> None:
    """Refuse a take that does not fit: estimate + storage.min_free_gb + the finishing reserve."""
    free = free_bytes(folder)
    take = estimate_take_bytes(rig, duration_s)
    need = take + rig.storage.min_free_gb * 1e9 + BALLAST_BYTES
    if free < need:
        cams = len(rig.cameras)
        raise DiskSpaceError(
            f"{folder}: not enough free disk: the take needs {need / 1e9:.2f} GB ({cams} cameras x "
            f"{rig.fps:g} FPS x {duration_s:g} s ~ {take / 1e9:.2f} GB, plus storage.min_free_gb "
            f"{rig.storage.min_free_gb:g} GB kept free), {free / 1e9:.2f} GB are free")
