"""What a take's files say besides the frame times (docs/sync.md, "The take's files"): take.json's
status, each camera's video against its frames.csv rows and take.json's count, and rows of
cameras take.json does not list. Videos are counted by Take.video_frames: from their
Matroska element headers, an imported AVI from its packets; no frame is decoded."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from manus_core.frames_csv import FILE_NAME as FRAMES_CSV
from manus_core.take import Take

KILLED_STATUS = "recording"   # take.json keeps it from the start until the recorder finishes


@dataclass(frozen=True)
class TakeFiles:
    """The checks of a take's files: per camera the fields the report adds to its entry
    (video_frames, video_problem, take_json_frames), and the findings."""

    status: str | None
    cameras: dict[str, dict] = field(default_factory=dict)
    unknown_camera_rows: dict[str, int] = field(default_factory=dict)
    reasons: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def killed(self) -> bool:
        return self.status == KILLED_STATUS


def camera_entries(meta: Mapping) -> dict[str, Mapping]:
    """take.json's camera objects by id (cameras given as bare ids have none)."""
    return {str(c["id"]): c for c in meta.get("cameras", []) if isinstance(c, Mapping) and "id" in c}


def lost_cameras(meta: Mapping) -> set[str]:
    """Cameras take.json marks as lost during the take (status other than ok)."""
    return {cam for cam, c in camera_entries(meta).items() if c.get("status", "ok") != "ok"}


def _video(take: Take, cam: str, rows: int, files: TakeFiles, recovered: bool) -> None:
    path = take.video_file(cam)
    name = path.relative_to(take.path).as_posix() if path.is_relative_to(take.path) else str(path)
    entry = files.cameras[cam]
    if not path.is_file():
        entry.update(video_frames=None, video_problem="missing")
        files.reasons.append(f"{cam}: {name} missing ({rows} frames.csv rows have no image)")
        return
    frames, problem = take.video_frames(cam)
    entry.update(video_frames=frames, video_problem=problem)
    why = f" ({problem})" if problem else ""
    if frames < rows:
        files.reasons.append(f"{cam}: {name} holds {frames} frames, frames.csv {rows} rows: the last "
                             f"{rows - frames} have no image{why}")
    elif frames > rows and (files.killed or recovered):
        # packets are written before their rows: a killed recorder leaves a few without one
        files.notes.append(f"{cam}: {name} holds {frames - rows} frames after its last frames.csv row, "
                           "written before the recorder was killed; they have no timestamps and are not used")
    elif frames > rows:
        files.reasons.append(f"{cam}: {name} holds {frames} frames, frames.csv only {rows} rows: "
                             f"{frames - rows} frames have no timestamps (rows lost)")
    elif problem:
        files.notes.append(f"{cam}: {name}: {problem}; every frame with a frames.csv row is there")


def check_files(take: Take) -> TakeFiles:
    """The take's status, every camera's video (frame count against frames.csv and take.json),
    and the frames.csv rows of cameras take.json does not list."""
    status = take.meta.get("status")
    files = TakeFiles(status if isinstance(status, str) else None)
    if files.killed and take.recorder_running:
        files.reasons.append(f"take.json: status '{KILLED_STATUS}': still being recorded by process "
                             f"{take.meta['recorder']['pid']}; check it when the take has ended")
    elif files.killed:
        files.reasons.append(f"take.json: status '{KILLED_STATUS}': the recorder was killed before it finished "
                             f"this take; `manus-capture recover {take.path}` finishes it")
    elif files.status == "interrupted":
        files.notes.append(f"the take was interrupted ({take.meta.get('reason') or 'no reason given'}): it ends "
                           "early, and frames lost after a camera's last one are not counted")
    recovered = "recovered" in take.meta
    entries, lost = camera_entries(take.meta), lost_cameras(take.meta)
    for cam in take.cameras:
        rows = take.frame_count(cam)
        files.cameras[cam] = {}
        _video(take, cam, rows, files, recovered)
        said = entries.get(cam, {}).get("frames")
        if not files.killed and isinstance(said, int):
            files.cameras[cam]["take_json_frames"] = said
            if said != rows:
                files.reasons.append(f"{cam}: take.json says {said} frames, frames.csv has {rows} rows")
        if cam in lost:
            c = entries[cam]
            files.reasons.append(f"{cam}: lost during the take ({c.get('status')}: {c.get('error') or 'no reason'})")
    names, counts = np.unique(take.frames["cam"], return_counts=True)
    files.unknown_camera_rows.update({str(n): int(k) for n, k in zip(names, counts) if n not in take.cameras})
    if files.unknown_camera_rows:
        listed = ", ".join(f"{n} ({k})" for n, k in files.unknown_camera_rows.items())
        files.reasons.append(f"{FRAMES_CSV}: {sum(files.unknown_camera_rows.values())} rows of cameras take.json "
                             f"does not list, left out: {listed}")
    return files
