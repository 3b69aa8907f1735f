"""Finishing a take whose recorder was killed (SIGKILL, a crash, power cut to the process).

The recorder writes each packet before its frames.csv row and keeps take.json at status
"recording" until it ends, so a killed take still holds every frame that has a row, readable,
and says it was never finished. `recover_take` makes such a take whole again without touching a
frame: it rebuilds the per-camera counts of take.json from frames.csv and the videos, marks the
take "interrupted" with the reason, gives back the disk reserve and updates session.toml.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from manus_core.errors import RecordError
from manus_core.fileio import write_atomic
from manus_core.session import load_session
from manus_core.take import Take

from .disk import RESERVE_NAME


def killed(take: Take) -> bool:
    """A take left at status "recording" by a recorder that is no longer running."""
    return take.meta.get("status") == "recording" and not take.recorder_running


@dataclass(frozen=True)
class Recovered:
    """What recover_take found: frames per camera and the packets without a frames.csv row."""

    path: Path
    frames: dict[str, int]
    packets_without_row: dict[str, int]
    rows_without_packet: dict[str, int]

    @property
    def total(self) -> int:
        return sum(self.frames.values())


def _seq_gaps(seq: np.ndarray) -> int:
    steps = np.diff(seq)
    return int(np.clip(steps - 1, 0, None).sum()) if len(steps) else 0


def recover_take(path: str | Path) -> Recovered:
    """Finish a killed take (see the module doc); RecordError names take.json when it is not one."""
    take = Take(path)
    meta_file = take.path / "take.json"
    status = take.meta.get("status")
    if status != "recording":
        raise RecordError(f"{meta_file}: status is {status!r}, not 'recording': the take was finished, "
                          f"nothing to recover")
    if take.recorder_running:
        who = take.meta["recorder"]
        raise RecordError(f"{meta_file}: still being recorded by process {who['pid']} on {who['host']}")
    frames, extra, missing = {}, {}, {}
    meta = dict(take.meta)
    reports = [dict(c) if isinstance(c, dict) else {"id": str(c)} for c in meta["cameras"]]
    for report in reports:
        cam = report["id"]
        rows = take.camera_frames(cam)
        packets = sum(1 for _ in take.packets(cam)) if take.video_path(cam).is_file() else 0
        n = len(rows["seq"])
        frames[cam] = n
        extra[cam], missing[cam] = max(packets - n, 0), max(n - packets, 0)
        report.update(frames=n, bytes=int(rows["bytes"].sum()), seq_gaps=_seq_gaps(rows["seq"]),
                      first_seq=int(rows["seq"][0]) if n else None, last_seq=int(rows["seq"][-1]) if n else None)
        if missing[cam]:
            report.update(status="error", error=f"{missing[cam]} frames.csv rows have no packet in its video")
    reason = (f"recorder killed mid-take (take.json was left 'recording'); recovered {sum(frames.values())} "
              f"frames from frames.csv and the videos")
    meta.update(cameras=reports, status="interrupted", reason=reason, frames=sum(frames.values()),
                recovered={"packets_without_row": extra, "rows_without_packet": missing})
    write_atomic(meta_file, json.dumps(meta, indent=1).encode())
    (take.path / RESERVE_NAME).unlink(missing_ok=True)
    session = load_session(take.path.parent)
    if session is not None and session.take(take.path.name) is not None:
        session.update_take(take.path.name, status="interrupted", reason=reason, frames=sum(frames.values()))
    return Recovered(take.path, frames, extra, missing)
