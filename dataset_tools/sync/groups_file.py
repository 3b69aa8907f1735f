"""TAKE/frame_groups.npz: a take's frame groups, saved beside the sync report that measured them.

    cameras (C,) str, frame_ns (T,) int64, frame_index (T,C) int64 (-1: no frame of the camera),
    exposure_ns (T,C) float64 (NaN: none), meta: JSON {"version", "method", "settings", "frames_sha256"}

The groups index the rows of one frames.csv: `load_groups` refuses them when the take's
frames.csv or camera list is no longer the one they were made from, rather than hand a later
stage groups the user never checked.
"""

from __future__ import annotations

import io
import json
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from manus_core.errors import SyncError
from manus_core.fileio import write_atomic
from manus_core.frames_csv import FILE_NAME as FRAMES_CSV
from manus_core.frames_csv import frames_csv_digest
from manus_core.take import Take

GROUPS_FILE = "frame_groups.npz"
GROUPS_VERSION = 1
SYNC_METHOD = "sync (fitted device clocks)"
HOST_METHOD = "host-time rounding (frames.csv)"
# an imported release's own alignment (its synced videos are index-aligned): the sync report keeps it
RELEASE_METHOD = "release (synced videos, index-aligned)"


@dataclass(frozen=True, eq=False)
class TakeGroups:
    """A take's frame groups as every stage after the sync report uses them.

    frame_ns (T,): each group's tick on the host clock; frame_index (T,C): each camera's frame
    index (its row of frames.csv) in the group, -1 where it has none, cameras in take.json order;
    exposure_ns (T,C): each member's estimated host-clock mid-exposure (its host arrival where the
    take was grouped on arrivals), NaN where none. method: SYNC_METHOD or HOST_METHOD; settings:
    what the grouping depended on (fps, t0_ns, the latency floor per camera); frames_sha256: the
    frames.csv they index; path: the file they were read from (None: computed, not saved).
    """

    cameras: tuple[str, ...]
    frame_ns: np.ndarray
    frame_index: np.ndarray
    exposure_ns: np.ndarray
    method: str
    settings: dict
    frames_sha256: str
    path: Path | None = None

    @property
    def description(self) -> str:
        """Where the groups came from, for the records of later stages."""
        return f"{self.method}, {GROUPS_FILE} of the sync report" if self.path else f"{self.method}, computed"


def save_groups(take_dir: str | Path, groups: TakeGroups) -> Path:
    """Write TAKE/frame_groups.npz atomically."""
    meta = {"version": GROUPS_VERSION, "method": groups.method, "settings": groups.settings,
            "frames_sha256": groups.frames_sha256}
    buf = io.BytesIO()
    np.savez(buf, cameras=np.array(groups.cameras, dtype=str), frame_ns=np.asarray(groups.frame_ns, np.int64),
             frame_index=np.asarray(groups.frame_index, np.int64),
             exposure_ns=np.asarray(groups.exposure_ns, np.float64), meta=np.array(json.dumps(meta)))
    path = Path(take_dir) / GROUPS_FILE
    write_atomic(path, buf.getvalue())
    return path


def load_groups(take: Take) -> TakeGroups | None:
    """The saved groups of a take; None when it has none. SyncError when the file is unreadable or
    was made from another frames.csv or camera list than the take's."""
    path = take.path / GROUPS_FILE
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as f:
            cameras = tuple(str(c) for c in f["cameras"])
            frame_ns, frame_index = f["frame_ns"].astype(np.int64), f["frame_index"].astype(np.int64)
            exposure_ns = f["exposure_ns"].astype(np.float64)
            meta = json.loads(str(f["meta"]))
        method, settings, digest = meta["method"], meta["settings"], meta["frames_sha256"]
    except (OSError, ValueError, KeyError, TypeError, zipfile.BadZipFile) as exc:
        raise SyncError(f"{path}: not a frame-groups file ({exc}); rerun `manus-capture sync-report "
                        f"{take.path} --force`") from None
    if not frame_index.shape == exposure_ns.shape == (len(frame_ns), len(cameras)):
        raise SyncError(f"{path}: frame_index {frame_index.shape} and exposure_ns {exposure_ns.shape} are not "
                        f"({len(frame_ns)} groups, {len(cameras)} cameras)")
    if cameras != take.cameras or digest != frames_csv_digest(take.path / FRAMES_CSV):
        raise SyncError(f"{path}: made from another {FRAMES_CSV} or camera list than the take has now; rerun "
                        f"`manus-capture sync-report {take.path} --force`")
    return TakeGroups(cameras, frame_ns, frame_index, exposure_ns, method, settings, digest, path)
