"""calibrate_rig: every camera of a take (or of per-camera image lists) in one call.

Methods:
- "tags": tag PnP per camera and one bundle adjustment (tag_rig.calibrate_tag_rig); cameras
  short of tags are then resected from scene features the others triangulate (features.py);
- "board": a board seen by several cameras at once (board_rig.calibrate_board_rig);
- "colmap": COLMAP structure from motion, moved into the tag world frame (colmap.py);
- "both": COLMAP and tags; cameras short of tags that the scene features cannot place keep their
  COLMAP pose inside the tag adjustment, and the report compares the two methods camera by camera;
- "auto": tags when a tag layout is given, else board.
Intrinsics are fixed from a file (--intrinsics), calibrated per camera from a board seen in the
same take, or, with neither, estimated per camera from the tags it sees and adjusted with its
pose (tag_intrinsics); the report gives their standard deviations and names weak cameras.
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from manus_core.cameras import CameraRig
from manus_core.errors import BoardError, CalibrationError, ColmapError, IntrinsicsError
from manus_core.progress import Progress, silent
from manus_core.take import Take

from ..sync import frame_groups
from .board_rig import calibrate_board_rig
from .boards import Board, TagLayout, load_board, load_tags
from .colmap import align_to_tags, colmap_poses
from .detect import Detection, TagDetector, detect_cameras
from .diagnose import diagnose_board
from .features import scene_anchors
from .formats import load_cameras, save_cameras
from .frames import FrameSource, read_frames, subsample, unreadable
from .intrinsics import calibrate_intrinsics
from .layout_check import OFF_MM, REFINED_OFF_MM, check_layout
from .report import build_report, cross_check, scale_check, write_report
from .result import RigCalibration, require_all
from .tag_intrinsics import TagIntrinsics, corner_table, estimate_intrinsics, without_poor_tags, without_tags
from .tag_rig import SceneCallback, calibrate_tag_rig, evaluate_tag_rig

METHODS = ("auto", "tags", "board", "colmap", "both")
EXPORTS = (("colmap", "colmap"), ("opencv-yaml", "cameras.yml"), ("easymocap", "easymocap"),
           ("manus", "optim_params.txt"))


Images = dict[str, Sequence[str | os.PathLike | np.ndarray] | str | os.PathLike]


def calibrate_rig(images: Images | None = None, *, take: str | os.PathLike | None = None,
                  tags: TagLayout | str | os.PathLike | None = None, board: Board | str | os.PathLike | None = None,
                  method: str = "auto", intrinsics: CameraRig | str | os.PathLike | None = None,
                  allow_partial: bool = False, tag_frames: int = 5, board_frames: int = 200,
                  refine_tags: bool = False, workers: int | None = None, output: str | os.PathLike | None = None,
                  force: bool = False, progress: Progress = silent) -> RigCalibration:
    """Calibrate every camera; write cameras.json, exports and the report when `output` is given.

    images: {camera: image paths, in-memory images, or one video path}; or take: a take folder.
    For a moving board, frame i of every camera must be the same instant (takes are grouped by
    their host timestamps). tag_frames / board_frames: how many frames per camera are used.
    workers: processes for the detection and threads for COLMAP (None: all cores; 1 makes COLMAP's
    model the same on every run).
    progress(stage, done, total): "board detection" and "tag detection" count cameras; the other
    stages (COLMAP, the adjustments, scene features) report (stage, 0, 1) as they start.
    Raises CalibrationError (and friends) naming the cameras when the input cannot be used;
    with allow_partial the cameras that cannot be calibrated are left out and the result says so.
    """
    layout = load_tags(tags) if isinstance(tags, (str, os.PathLike)) else tags
    target = load_board(board) if isinstance(board, (str, os.PathLike)) else board
    if method not in METHODS:
        raise CalibrationError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if method == "auto":
        method = "tags" if layout is not None else "board"
    if method in ("tags", "colmap", "both") and layout is None:
        raise CalibrationError(f"method '{method}' needs a tag layout (--tags tags.json): it sets the world frame "
                               f"and the metric scale")
    if method == "board" and target is None:
        raise CalibrationError("method 'board' needs a board (--board board.toml)")
    if output is not None and not force and (Path(output) / "cameras.json").exists():
        raise CalibrationError(f"{Path(output) / 'cameras.json'}: exists; pass --force to replace it")
    sources, sync = _sources(images, take)
    cams = list(sources)
    fixed = _fixed_intrinsics(intrinsics, cams, allow_partial)
    problems: dict[str, str] = {c: "not in the intrinsics file" for c in cams if fixed is not None and c not in fixed}
    # an unreadable video is found now, in this process, so that it costs its camera only
    problems.update({c: why for c, src in sources.items() if c not in problems and (why := unreadable(src))})
    require_all(cams, problems, allow_partial)
    checks: dict = {}
    inputs = {"cameras": len(cams), "method": method, "take": str(take) if take else None}

    board_dets = sizes = None
    if target is not None and (method == "board" or fixed is None):
        board_src = {c: subsample(s, board_frames) for c, s in sources.items() if c not in problems}
        board_dets, sizes = detect_cameras(board_src, target, workers, progress)
        board_dets = {c: {sync[c](f): d for f, d in dets.items()} for c, dets in board_dets.items()}
        _no_board(board_dets, board_src, target, problems)
    if method == "board":
        require_all(cams, problems, allow_partial)
        keep = {c: d for c, d in board_dets.items() if c not in problems}
        given = {c: fixed[c] for c in keep} if fixed is not None else None
        progress("bundle adjustment of cameras, intrinsics and board poses", 0, 1)
        result = calibrate_board_rig(keep, sizes, target, intrinsics=given, refine_intrinsics=given is None,
                                     allow_partial=allow_partial)
        result = _with_missing(result, problems)
        checks["scale"] = scale_check(result, target.neighbour_pairs(), target.neighbour_distance())
    else:
        intr = fixed if fixed is not None else _board_intrinsics(board_dets, sizes, target, problems)
        estimated: dict[str, TagIntrinsics | str] = {}
        if not intr:
            # no file and no board: every camera's intrinsics from the tags it sees (as MANUS did)
            first = {c: subsample(sources[c], tag_frames) for c in cams if c not in problems}
            found, first_sizes = detect_cameras(first, TagDetector(layout.dictionary), workers, progress)
            estimated = _estimate(found, first_sizes, layout)
            intr = _with_borrowed(estimated, first_sizes)
            # a camera with neither its own estimate nor one to borrow is named, never dropped silently
            problems.update({c: f"no intrinsics: it {e}" for c, e in estimated.items() if c not in intr})
        if not intr:
            raise CalibrationError("no camera has intrinsics: pass --intrinsics FILE or a --board seen in the take"
                                   + (f" ({'; '.join(f'{c}: {m}' for c, m in problems.items())})" if problems else ""))
        require_all(cams, problems, allow_partial)
        tag_src = {c: subsample(sources[c], tag_frames) for c in cams if c in intr and c not in problems}
        detectors = {c: TagDetector(layout.dictionary, K=intr[c][0], dist=intr[c][1]) for c in tag_src}
        tag_dets, tag_sizes = detect_cameras(tag_src, detectors, workers, progress)
        _check_sizes(tag_sizes, intr)
        if estimated:
            # the corners found with the first estimate straighten the tags' edges: estimate again
            estimated = {c: e if isinstance(e, str) else _estimate({c: tag_dets[c]}, tag_sizes, layout)[c]
                         for c, e in estimated.items() if c in tag_dets}
            intr = _with_borrowed(estimated, tag_sizes)
            # the adjustment estimates intrinsics from the same corners the estimate trusted
            tag_dets = {c: without_poor_tags(d) if isinstance(estimated.get(c), TagIntrinsics) else d
                        for c, d in tag_dets.items()}
        initial, colmap_rig = {}, None
        if method in ("colmap", "both"):
            progress("COLMAP: features, matching, mapping", 0, 1)
            try:
                colmap_rig, info = _colmap(tag_src, tag_dets, tag_sizes, intr, layout, workers)
            except ColmapError as exc:
                if method == "colmap":
                    raise
                info = {"error": str(exc)}  # "both" goes on with the tags and reports why
            inputs["colmap"] = info
            if colmap_rig is not None:
                initial = {c: _pose(colmap_rig, c) for c in colmap_rig.ids}
        if method == "colmap":
            result = evaluate_tag_rig(colmap_rig, tag_dets, layout, "colmap", extra=inputs["colmap"])
            lost = {c: "not registered by COLMAP" for c in tag_src if c not in colmap_rig.ids}
            problems.update(lost)
            require_all(cams, problems, allow_partial)
            result = _with_missing(result, problems)
        else:
            progress("tag PnP and bundle adjustment", 0, 1)

            def solve(dets: dict[str, dict[int, Detection]], tags: TagLayout) -> RigCalibration:
                return calibrate_tag_rig(dets, tag_sizes, tags, intr, refine_tags=refine_tags,
                                         allow_partial=allow_partial, initial_poses=initial or None,
                                         scene=_scene(tag_src, dets, progress),
                                         free_intrinsics={c: e.free() for c, e in estimated.items()
                                                          if isinstance(e, TagIntrinsics)})
            result = solve(tag_dets, layout)
            checks["layout"] = check_layout(result.rig, tag_dets, layout, REFINED_OFF_MM if refine_tags else OFF_MM)
            if checks["layout"]["disagreeing"]:
                # the tags tags.json misplaces are named in the report and left out of a second solve
                wrong = [int(t) for t in checks["layout"]["disagreeing"]]
                progress(f"bundle adjustment again without tags {', '.join(map(str, wrong))}", 0, 1)
                tag_dets = {c: {f: without_tags(d, wrong) for f, d in dets.items()} for c, dets in tag_dets.items()}
                layout = layout.without(wrong)
                result = solve(tag_dets, layout)
            result = _with_missing(result, problems)
            if colmap_rig is not None:
                checks["cross_check"] = cross_check(evaluate_tag_rig(colmap_rig, tag_dets, layout, "colmap"), result)
                result = replace(result, method="both")
        checks["scale"] = scale_check(result, layout.edge_pairs(), layout.size, static=True)
        if estimated:
            result.extra["intrinsics"] = _intrinsics_record(estimated, result.extra.get("intrinsics", {}))
    result.extra["checks"] = checks
    report = build_report(result, inputs, checks)
    if output is not None:
        _write_outputs(result, report, Path(output), layout)
    return result


def _with_missing(result: RigCalibration, problems: dict[str, str]) -> RigCalibration:
    """The result with the cameras left out before it was computed added to those it left out."""
    missing = {**result.missing, **problems}
    return replace(result, missing=missing, partial=bool(missing))


def _sources(images: Images | None, take) -> tuple[dict[str, FrameSource], dict[str, Callable[[int], int]]]:
    """Per camera: where its frames are, and the map from its frame index to a sync index."""
    if (images is None) == (take is None):
        raise CalibrationError("give either per-camera images or a take folder")
    if take is not None:
        return _take_sources(Path(take))
    sources = {}
    for cam, value in images.items():
        if isinstance(value, (str, os.PathLike)):
            sources[str(cam)] = FrameSource((str(value),))
        elif len(value) and all(isinstance(v, np.ndarray) for v in value):
            sources[str(cam)] = FrameSource(arrays=tuple(value))
        else:
            sources[str(cam)] = FrameSource(tuple(str(v) for v in value))
    if not sources:
        raise CalibrationError("no cameras given")
    return sources, {c: _identity for c in sources}


def _identity(i: int) -> int:
    return i


def _take_sources(path: Path) -> tuple[dict[str, FrameSource], dict[str, Callable[[int], int]]]:
    """A take's videos, and per camera its frame index -> the frame group of the sync stage
    (dataset_tools.sync.frame_groups: the groups its sync report saved, or computed the same way).
    A frame in no group gets a key of its own, so it is never paired with another camera's."""
    take = Take(path)
    groups = frame_groups(take)
    sources, sync = {}, {}
    for c, cam in enumerate(groups.cameras):
        sources[cam] = FrameSource((str(path),), camera=cam)
        count = take.frame_count(cam)
        key = len(groups.frame_ns) + c * count + np.arange(count, dtype=np.int64)
        member = np.flatnonzero(groups.frame_index[:, c] >= 0)
        key[groups.frame_index[member, c]] = member
        sync[cam] = key.__getitem__
    return sources, sync


def _fixed_intrinsics(intrinsics, cams: list[str], allow_partial: bool) -> dict[str, tuple[np.ndarray, np.ndarray]] | None:
    if intrinsics is None:
        return None
    if not isinstance(intrinsics, CameraRig):
        intrinsics = load_cameras(intrinsics)
    out = {c: (intrinsics.K[i], intrinsics.dist[i]) for i, c in enumerate(intrinsics.ids) if c in cams}
    missing = [c for c in cams if c not in out]
    if missing and not allow_partial:
        raise CalibrationError(f"cameras {', '.join(missing)} are not in the intrinsics file "
                               f"(it has {', '.join(intrinsics.ids[:8])}{'...' if len(intrinsics) > 8 else ''})")
    return out


def _no_board(dets: dict[str, dict[int, Detection]], sources: dict[str, FrameSource], board: Board,
              problems: dict[str, str]) -> None:
    """Cameras that never see the board: say which parameter of board.toml is likely wrong."""
    empty = [c for c, d in dets.items() if not d]
    if not empty:
        return
    sample = [g for _, g in read_frames(subsample(sources[empty[0]], 5))]
    why = diagnose_board(sample, board)
    if len(empty) == len(dets):
        raise BoardError(f"no camera sees the board ({', '.join(empty)}): {why}")
    for c in empty:
        problems[c] = f"never sees the board ({why})"


def _board_intrinsics(dets, sizes, board, problems) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    out = {}
    if dets is None:
        return out
    for cam, d in dets.items():
        if cam in problems:
            continue
        try:
            res = calibrate_intrinsics(d, board, sizes[cam], camera=cam)
        except IntrinsicsError as exc:
            problems[cam] = exc.reason
            continue
        out[cam] = (res.K, res.dist)
    return out


def _estimate(dets: dict[str, dict[int, Detection]], sizes: dict[str, tuple[int, int]], layout: TagLayout
              ) -> dict[str, TagIntrinsics | str]:
    """Each camera's intrinsics from its tag corners (tag_intrinsics), or why they cannot be had."""
    pid, world = layout.points()
    lookup = {int(p): i for i, p in enumerate(pid)}
    return {c: estimate_intrinsics(*corner_table(d, lookup, world), sizes[c]) for c, d in dets.items()}


def _with_borrowed(estimated: dict[str, TagIntrinsics | str], sizes: dict[str, tuple[int, int]]
                   ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """(K, dist) per camera: its own estimate, or, for a camera whose tags cannot give one, the
    median focal length of the estimated cameras of its image size, centred, without distortion:
    enough to place it from its few tags or the scene; the report names it."""
    own = {c: (e.K, e.dist) for c, e in estimated.items() if isinstance(e, TagIntrinsics)}
    out = dict(own)
    for c, e in estimated.items():
        same = [K[0, 0] / sizes[o][0] for o, (K, _) in own.items() if sizes[o] == sizes[c]]
        if isinstance(e, str) and same:
            w, h = sizes[c]
            f = float(np.median(same)) * w
            out[c] = (np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]]), np.zeros(5))
    return out


def _intrinsics_record(estimated: dict[str, TagIntrinsics | str], adjusted: dict[str, dict]) -> dict[str, dict]:
    """report.json's per-camera account of intrinsics estimated from the tags."""
    out = {}
    for c, e in estimated.items():
        if isinstance(e, str):
            out[c] = {"model": None, "borrowed": e, "weak": [f"intrinsics not estimated: it {e}; the other "
                                                             "cameras' median focal length was used"]}
        else:
            out[c] = {"model": e.model, "points": e.points, "reach": round(e.reach, 3), **adjusted.get(c, {})}
    return out


def _check_sizes(sizes: dict[str, tuple[int, int]], intr) -> None:
    """Intrinsics from a file must belong to images of the same size."""
    bad = []
    for cam, (w, h) in sizes.items():
        K = intr[cam][0]
        if not (0 < K[0, 2] < w and 0 < K[1, 2] < h):
            bad.append(f"{cam} ({w}x{h}, principal point {K[0, 2]:.0f},{K[1, 2]:.0f})")
    if bad:
        raise CalibrationError(f"the intrinsics do not fit the images of cameras {', '.join(bad)}: "
                               f"were they calibrated at another resolution?")


def _colmap(sources, tag_dets, sizes, intr, layout, workers: int | None):
    """COLMAP on one frame per camera (the one with most tag corners), aligned to the tags; on
    `workers` threads (all cores when None). One thread gives the same model on every run: COLMAP
    is seeded, but its threads finish in any order (the alignment to the tags measured 1.9-2.8 mm
    RMS over runs on all cores, and 5.6 mm once under load)."""
    images, dets = {}, {}
    for cam, src in sources.items():
        frame, images[cam] = _best_frame(src, tag_dets.get(cam, {}))
        dets[cam] = tag_dets.get(cam, {}).get(frame)
    poses, stats = colmap_poses(images, intr, threads=workers or -1)
    rig, info = align_to_tags(poses, intr, sizes, {c: d for c, d in dets.items() if d is not None}, layout)
    return rig, {**stats, **info}


def _best_frame(source: FrameSource, found: dict[int, Detection]) -> tuple[int, np.ndarray]:
    """The frame of a static camera with most tag corners (the first one read when it sees none)."""
    frame = max(found, key=lambda f: len(found[f])) if found else (source.frames[0] if source.frames else 0)
    return frame, next(g for _, g in read_frames(FrameSource(source.paths, (frame,), source.arrays, source.camera)))


def _scene(sources: dict[str, FrameSource], tag_dets: dict[str, dict[int, Detection]],
           progress: Progress) -> SceneCallback:
    """tag_rig.calibrate_tag_rig's `scene`: one image per camera, read only when a camera is
    short of tags. (The mean of a static camera's frames, with less noise, placed the cameras no
    better: what limits them is the few, weak features they share with the others.)"""
    def anchors(calibrated: CameraRig, targets: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict:
        progress(f"scene features for {len(targets)} camera(s) short of tags", 0, 1)
        images = {c: _best_frame(sources[c], tag_dets.get(c, {}))[1] for c in (*calibrated.ids, *targets)
                  if c in sources}
        return scene_anchors(images, calibrated, targets)
    return anchors


def _pose(rig: CameraRig, cam: str) -> np.ndarray:
    i = rig.index(cam)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rig.R[i], rig.t[i]
    return T


def _write_outputs(result: RigCalibration, report: dict, folder: Path, layout: TagLayout | None) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    exported = {}
    for fmt, name in EXPORTS:
        try:
            save_cameras(result.rig, folder / name, fmt, lossy=True)
            exported[fmt] = name
        except ValueError as exc:  # a camera id a format cannot hold: skip that export, say why
            exported[fmt] = f"not written: {exc}"
    report["exports"] = exported
    points = layout.corners.reshape(-1, 3) if layout is not None else None
    write_report(result, folder, report, points)
    # cameras.json last: its presence means the calibration folder is complete
    save_cameras(result.rig, folder / "cameras.json", "json")
