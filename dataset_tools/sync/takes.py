"""The sync stage on a take folder: `sync_take` writes TAKE/sync_report.json, .md, the timeline PNG
and the frame groups it measured (frame_groups.npz); `frame_groups` is what every later stage
calls to get a take's groups (the saved ones, else the same grouping computed now)."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import cv2
import numpy as np

from manus_core.errors import SyncError, SyncReportExists, TakeError
from manus_core.fileio import write_atomic
from manus_core.frames_csv import FILE_NAME as FRAMES_CSV
from manus_core.frames_csv import frames_csv_digest
from manus_core.progress import Progress, silent
from manus_core.take import Take

from .analysis import SYNC_MODES, SyncResult, SyncSettings, analyze_sync
from .files import camera_entries, check_files, lost_cameras
from .grouping import group_frames
from .groups_file import GROUPS_FILE, HOST_METHOD, RELEASE_METHOD, SYNC_METHOD, TakeGroups, load_groups, save_groups
from .optical import BrightnessFn, Flash, led_flashes, optical_check
from .report import build_report, report_markdown, timeline_png

REPORT_FILE = "sync_report.json"


def _take_latency(meta: Mapping, cams: Sequence[str]) -> dict[str, float]:
    """Per camera latency floor from take.json camera objects: exposure_us / 2 + latency_ms (end of
    exposure -> earliest host arrival), where latency_ms is given (at the top or in "sim")."""
    out = {}
    for cam, entry in camera_entries(meta).items():
        lat = entry.get("latency_ms", (entry.get("sim") or {}).get("latency_ms"))
        if cam in cams and isinstance(lat, (int, float)):
            exposure = entry.get("exposure_us")
            half_exposure = float(exposure) * 500 if isinstance(exposure, (int, float)) else 0.0
            out[cam] = float(lat) * 1e6 + half_exposure
    return out


def _take_t0(meta: Mapping) -> int | None:
    for key in ("t0_ns", "start_ns"):
        if isinstance(meta.get(key), int):
            return int(meta[key])
    return None


def _take_end(meta: Mapping) -> int | None:
    """When the recorder ended a take that ran to its end (t0_ns + duration_s), else None."""
    t0, duration = _take_t0(meta), meta.get("duration_s")
    if meta.get("status") != "complete" or t0 is None or not isinstance(duration, (int, float)):
        return None
    return t0 + int(round(duration * 1e9))


def _open(path: Take | str | Path) -> Take:
    return path if isinstance(path, Take) else Take(path)


def take_brightness(take: Take) -> BrightnessFn:
    """Mean brightness of chosen frames of a take: packets are read without decoding and only the
    wanted ones are decoded, at 1/8 scale in grey (JPEG DCT scaling, no full decode)."""

    def brightness(cam: str, indices: np.ndarray) -> np.ndarray:
        wanted = {int(i): j for j, i in enumerate(indices)}
        out = np.full(len(indices), np.nan)
        last = max(wanted) if wanted else -1
        for k, packet in enumerate(take.packets(cam)):
            if k > last:
                break
            if k in wanted:
                image = cv2.imdecode(packet, cv2.IMREAD_REDUCED_GRAYSCALE_8)
                if image is None:
                    raise TakeError(f"{take.video_path(cam)}: frame {k} is not a decodable JPEG")
                out[wanted[k]] = float(image.mean())
        return out

    return brightness


def take_flashes(take: Take) -> list[Flash]:
    """The LED flashes of a take: take.json's LED command log ("led_log", or "leds")."""
    log = take.meta.get("led_log", take.meta.get("leds"))
    return led_flashes(log) if isinstance(log, list) else []


def _analyze(take: Take, latency_ns: Mapping[str, float] | None,
             settings: SyncSettings | None) -> tuple[SyncResult, dict[str, float]]:
    """The sync analysis of a take's frames.csv with take.json's fps, sync mode, t0 and latency
    floors (`latency_ns` overrides the floors): the result and the floors it used."""
    meta_path = take.path / "take.json"
    if take.fps is None or take.fps <= 0:
        raise SyncError(f"{meta_path}: fps: missing or not a positive number (the ticks need it)")
    sync = take.meta.get("sync", "free-run")
    if sync not in SYNC_MODES:
        raise SyncError(f"{meta_path}: sync: {sync!r} is not one of {', '.join(SYNC_MODES)}")
    frames = {cam: take.camera_frames(cam) for cam in take.cameras}
    latency = {**_take_latency(take.meta, take.cameras), **(latency_ns or {})}
    result = analyze_sync(frames, take.fps, sync=sync, t0_ns=_take_t0(take.meta), latency_ns=latency,
                          settings=settings, end_ns=_take_end(take.meta), lost=lost_cameras(take.meta))
    return result, latency


def _sync_groups(take: Take, result: SyncResult, latency: Mapping[str, float]) -> TakeGroups:
    g = result.groups
    order = [g.cameras.index(c) for c in take.cameras]
    settings = {"fps": result.fps, "t0_ns": result.t0_ns, "latency_ns": dict(latency)}
    return TakeGroups(take.cameras, g.frame_ns, g.frame_index[:, order], g.exposure_ns[:, order], SYNC_METHOD,
                      settings, frames_csv_digest(take.path / FRAMES_CSV))


def _host_time_groups(take: Take) -> TakeGroups:
    """The same grouping on host arrival times, for takes the sync analysis refuses (no fps in
    take.json, or an unknown sync mode): arrivals stand in for exposures, and a missing fps is
    measured from them."""
    hosts = [take.camera_frames(cam)["t_host_ns"] for cam in take.cameras]
    if not any(len(h) for h in hosts):
        raise SyncError(f"{take.path / FRAMES_CSV}: no frames")
    fps = take.fps
    if not fps or fps <= 0:
        steps = np.concatenate([np.diff(np.sort(h)) for h in hosts if len(h) > 1] or [np.zeros(0)])
        if not len(steps):
            raise SyncError(f"{take.path / 'take.json'}: no fps and too few frames to measure it")
        fps = 1e9 / float(np.median(steps))
    g = group_frames([h.astype(np.float64) for h in hosts], fps, cameras=take.cameras)
    return TakeGroups(take.cameras, g.frame_ns, g.frame_index, g.exposure_ns, HOST_METHOD,
                      {"fps": fps, "t0_ns": g.t0_ns}, frames_csv_digest(take.path / FRAMES_CSV))


def frame_groups(path: Take | str | Path) -> TakeGroups:
    """A take's frame groups, the ones every stage after the sync report works on.

    The groups saved with the take's sync report (TAKE/frame_groups.npz) when there is one;
    otherwise the same analysis computes them now with the default settings (take.json's fps, t0
    and latency floors), or, where it cannot run, the same grouping of the host arrival times.
    Nothing is written."""
    take = _open(path)
    saved = load_groups(take)
    if saved is not None:
        return saved
    try:
        result, latency = _analyze(take, None, None)
    except SyncError:
        return _host_time_groups(take)
    return _sync_groups(take, result, latency)


def _validate(take: Take, latency_ns: Mapping[str, float] | None, optical: bool, settings: SyncSettings | None,
              progress: Progress) -> tuple[SyncResult, dict, dict[str, float]]:
    result, latency = _analyze(take, latency_ns, settings)
    flashes = take_flashes(take) if optical else []
    check = optical_check(result.cameras, flashes, take_brightness(take), t0_ns=result.t0_ns,
                          progress=progress) if flashes else None
    return result, build_report(result, check, take=take.path.name, files=check_files(take)), latency


def analyze_take(path: Take | str | Path, *, latency_ns: Mapping[str, float] | None = None, optical: bool = True,
                 settings: SyncSettings | None = None, progress: Progress = silent) -> tuple[SyncResult, dict]:
    """Run the sync validation on a take folder: (result, sync_report dict). Nothing is written."""
    result, report, _ = _validate(_open(path), latency_ns, optical, settings, progress)
    return result, report


def refuse_overwrite(take_path: Path, force: bool) -> Path:
    """TAKE/sync_report.json; raises SyncReportExists when it is there and `force` is not set."""
    target = Path(take_path) / REPORT_FILE
    if target.exists() and not force:
        raise SyncReportExists(f"{target}: exists (use --force to recompute)")
    return target


def sync_take(path: str | Path, *, force: bool = False, latency_ns: Mapping[str, float] | None = None,
              optical: bool = True, settings: SyncSettings | None = None, progress: Progress = silent) -> dict:
    """Validate a take and write TAKE/sync_report.json, sync_report.md, sync_timeline.png and the
    frame groups the report measured (frame_groups.npz, which later stages read). An imported
    release's own groups (RELEASE_METHOD) are kept: the release's videos define its alignment.

    Refuses (SyncReportExists) to replace an existing report unless `force`; each file is written
    atomically, the JSON last, so a report on disk always has its companions."""
    take = Take(path)
    target = refuse_overwrite(take.path, force)
    result, report, latency = _validate(take, latency_ns, optical, settings, progress)
    try:
        kept = load_groups(take)
    except SyncError:   # made from another frames.csv: replaced below
        kept = None
    release = kept is not None and kept.method == RELEASE_METHOD
    report["frame_groups"] = f"{GROUPS_FILE} ({RELEASE_METHOD}, kept)" if release else GROUPS_FILE
    write_atomic(take.path / "sync_timeline.png", timeline_png(result, take_flashes(take)))
    write_atomic(take.path / "sync_report.md", report_markdown(report).encode())
    if not release:
        save_groups(take.path, _sync_groups(take, result, latency))
    write_atomic(target, (json.dumps(report, indent=1) + "\n").encode())
    return report
