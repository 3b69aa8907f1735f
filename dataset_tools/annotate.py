"""The annotate stage: takes -> frame groups -> 2D keypoints -> triangulation -> bone lengths ->
inverse kinematics -> 1-euro filter -> DATASET.h5 (docs/annotate.md).

    summary = annotate(["S/hand_01", "S/grasp_01"], "CALIB", "DATASET.h5", workers=2)
    result = annotate_arrays(rig, keypoints2d, frame_ns, bone_lengths)   # the numeric core, no files

Takes are independent once the subject's bone lengths are known, so they run as tasks: inline
(workers=1), in a local process pool (workers=N) or on a Dask cluster (scheduler="tcp://HOST:PORT").
Every task returns its arrays to this process, which saves each finished take at once (see
dataset.DatasetWriter), so an interrupted run resumes with the takes it had not finished, and the
three ways of running give the same file.

Bone lengths, per session (the take folder's parent), first match wins:
1. `bones=` (a subject file, or 20 lengths) for every take;
2. SESSION/subjects/SUBJECT.json when it exists (SUBJECT from SESSION/session.toml, [session] subject);
3. the session's hand takes (take.json kind = "hand") among the takes of this run: their
   triangulated joints, robustly averaged (hand.bones), saved as (2) when the session names its
   subject;
4. the take itself.
Every take records where its bones came from (attribute bone_source).

A take already in the output (or saved by an interrupted run) is kept only when all its inputs
(annotate_inputs: frames, calibration, cameras, keypoints, frame groups, bones, settings) are the
same now; otherwise it is redone and the summary says why. Uncalibrated cameras are left out.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from manus_core.cameras import CameraRig
from manus_core.dataset import FLAGS, DatasetWriter, TakeAnnotation, skeleton_description, software_version, take_key
from manus_core.errors import AnnotateError, BoneLengthError
from manus_core.progress import Progress, silent
from manus_core.provenance import array_sha256, cameras_used, differences, file_sha256, provenance_attrs, stage_inputs
from manus_core.session import load_session
from manus_core.skeleton import HandSkeleton
from manus_core.take import Take

from .annotate_options import AnnotateOptions
from .calibration.formats import load_cameras
from .cross_view import recover_views
from .hand.bones import bone_lengths_from_samples, bone_samples, estimate_bone_lengths, load_subject, save_subject
from .hand.ik import fit_hand, unwrap_rotations, wrap_rotations
from .keypoints.keypoints2d import cached_detector
from .one_euro import one_euro
from .sync import GROUPS_FILE, frame_groups
from .take_keypoints import cross_view_model, keypoint_mode, take_keypoints
from .tasks import run_tasks
from .triangulation import triangulate_frames

Groups = tuple[np.ndarray, np.ndarray]  # frame_ns (T,), frame_index (T,C)


# --- the numeric core ------------------------------------------------------------------------------

def filter_angles(angles: np.ndarray, frame_ns: np.ndarray, options: AnnotateOptions = AnnotateOptions()) -> np.ndarray:
    """1-euro filter of joint angles (T,26) over time: the rotation vector is made continuous
    first (and brought back to [0, pi] after); the wrist translation (metres, not radians) gets
    its own beta. NaN samples stay NaN."""
    t = (np.asarray(frame_ns, np.int64) - int(frame_ns[0])) / 1e9
    x = unwrap_rotations(angles)
    rad = [0, 1, 2] + list(range(6, 26))
    out = np.empty_like(x)
    out[:, rad] = one_euro(x[:, rad], t, options.min_cutoff, options.beta, options.d_cutoff)
    out[:, 3:6] = one_euro(x[:, 3:6], t, options.min_cutoff, options.beta_translation, options.d_cutoff)
    return wrap_rotations(out)


def annotate_arrays(rig: CameraRig, keypoints2d: np.ndarray, frame_ns: np.ndarray,
                    bone_lengths: np.ndarray | None = None, options: AnnotateOptions = AnnotateOptions(),
                    skeleton: HandSkeleton | None = None) -> dict[str, np.ndarray]:
    """Triangulate, fit and filter one take's keypoints (T,C,21,3) seen by `rig`'s cameras.

    bone_lengths None: estimated from this take. Returns keypoints3d, keypoints3d_error_px,
    keypoints3d_views, joint_angles_raw, joint_angles, ik_residual_m, flags, bone_lengths,
    fitted (T,21,3, of the raw angles).
    """
    kp = np.asarray(keypoints2d, dtype=np.float64)
    frame_ns = np.asarray(frame_ns, dtype=np.int64)
    if kp.ndim != 4 or kp.shape[1:] != (len(rig), 21, 3) or len(frame_ns) != len(kp):
        raise AnnotateError(f"keypoints2d must be (T, {len(rig)}, 21, 3) with T = len(frame_ns) = {len(frame_ns)}, "
                            f"got shape {kp.shape}")
    if len(frame_ns) > 1 and (np.diff(frame_ns) <= 0).any():
        raise AnnotateError("frame_ns must increase strictly (one row per frame group)")
    X, err, used = triangulate_frames(rig, kp, threshold_px=options.threshold_px, min_views=options.min_views,
                                      return_inliers=True)
    found = np.isfinite(X).all(-1)
    if not found.any():
        raise AnnotateError(f"no joint could be triangulated in any of the {len(kp)} frames "
                            f"(keypoints missing or seen by fewer than {options.min_views} cameras)")
    if bone_lengths is None:
        bone_lengths = estimate_bone_lengths(X, err).bone_lengths
    angles, fitted, info = fit_hand(X, bone_lengths, skeleton=skeleton, min_joints=options.min_joints,
                                    return_info=True)
    filtered = filter_angles(angles, frame_ns, options)
    flags = np.zeros(len(kp), np.uint8)
    flags[~info.valid] |= FLAGS["no_hand"]
    flags[~found.all(1)] |= FLAGS["missing_joints"]
    with np.errstate(invalid="ignore"):
        flags[info.residual > options.ik_poor_m] |= FLAGS["ik_poor"]
    return {"keypoints3d": X, "keypoints3d_error_px": err, "keypoints3d_views": used.sum(1).astype(np.int16),
            "joint_angles_raw": angles, "joint_angles": filtered, "ik_residual_m": info.residual,
            "flags": flags, "bone_lengths": np.asarray(bone_lengths, np.float64), "fitted": fitted}


# --- tasks -----------------------------------------------------------------------------------------

@dataclass
class TakeTask:
    """Everything a worker needs for one take (picklable: runs in a process pool or on Dask)."""

    path: str
    key: str
    rig: CameraRig
    options: AnnotateOptions
    calibration: dict
    cameras: tuple[str, ...]
    inputs: dict
    bones: np.ndarray | None = None
    bone_source: str = "take"
    groups: Groups | None = None
    # (keypoints (T,C,21,3), source, views recovered) where this run has them already: a hand
    # take's, found for the subject's bones, are not detected a second time for its annotation
    keypoints: tuple[np.ndarray, str, int] | None = None


class _Prepared(NamedTuple):
    take: Take
    frame_ns: np.ndarray
    frame_index: np.ndarray    # (T,C) of the task's cameras
    keypoints: np.ndarray      # (T,C,21,3)
    source: str
    grouping: str
    recovered: int             # views the cross-view step filled in


def _prepare(task: TakeTask) -> _Prepared:
    take = Take(task.path)
    if task.groups is not None:
        frame_ns, frame_index = (np.asarray(a, np.int64) for a in task.groups)
        if frame_index.shape != (len(frame_ns), len(take.cameras)):
            raise AnnotateError(f"{take.path}: frame groups have frame_index {frame_index.shape}, expected "
                                f"({len(frame_ns)}, {len(take.cameras)}) for its cameras")
        grouping = "given"
    else:
        groups = frame_groups(take)
        frame_ns, frame_index, grouping = groups.frame_ns, groups.frame_index, groups.description
    used = [take.cameras.index(c) for c in task.cameras]
    if task.keypoints is not None:
        kp, source, recovered = task.keypoints
        return _Prepared(take, frame_ns, frame_index[:, used], kp, source, grouping, recovered)
    kp, source = take_keypoints(take, frame_index, task.options)
    frame_index, kp, recovered = frame_index[:, used], kp[:, used], 0
    model, o = cross_view_model(take, task.options), task.options
    if model is not None:
        kp, recovered = recover_views(take, task.rig, kp, frame_index, cached_detector(model, o.device, o.palm_tiles),
                                      o.threshold_px, o.min_views)
        source += "+cross-view"
    return _Prepared(take, frame_ns, frame_index, kp, source, grouping, recovered)


def hand_take_samples(task: TakeTask) -> tuple[np.ndarray, float, tuple[np.ndarray, str, int]]:
    """Per-frame bone lengths (T,20) of a hand take and the error threshold used (for the subject),
    and the take's keypoints, source and views recovered (TakeTask.keypoints, for its annotation)."""
    prepared = _prepare(task)
    X, err = triangulate_frames(task.rig, prepared.keypoints, threshold_px=task.options.threshold_px,
                                min_views=task.options.min_views)
    return *bone_samples(X, err), (prepared.keypoints, prepared.source, prepared.recovered)


def annotate_take(task: TakeTask) -> TakeAnnotation:
    """The whole stage for one take (runs in a worker)."""
    try:
        take, frame_ns, frame_index, kp, source, grouping, recovered = _prepare(task)
        result = annotate_arrays(task.rig, kp, frame_ns, task.bones, task.options)
    except (AnnotateError, BoneLengthError) as exc:
        raise AnnotateError(f"{task.path}: {exc}") from None
    flags = result["flags"]
    flags[(frame_index < 0).any(1)] |= FLAGS["incomplete_group"]
    attrs = {"kind": str(take.meta.get("kind", "")), "take": str(take.path), "status": "complete",
             "skeleton": skeleton_description(HandSkeleton(result["bone_lengths"])),
             "software": software_version(), "keypoint_source": source, "views_recovered": recovered,
             "bone_source": task.bone_source if task.bones is not None else "take", "filter": task.options.filter,
             "frame_groups": grouping, "cameras_left_out": [c for c in take.cameras if c not in task.cameras],
             **task.calibration, **provenance_attrs("annotate", task.inputs)}
    return TakeAnnotation(task.key, task.cameras, frame_ns, frame_index, kp.astype(np.float32),
                          result["keypoints3d"], result["keypoints3d_error_px"], result["keypoints3d_views"],
                          result["joint_angles_raw"], result["joint_angles"], result["bone_lengths"],
                          result["ik_residual_m"], flags, attrs)


# --- running many takes ----------------------------------------------------------------------------

def session_subject(session: Path) -> str | None:
    """The subject named by SESSION/session.toml (read by the session format's own reader, so a
    malformed file gives its SessionError); None when there is no file or it names no subject."""
    found = load_session(session)
    return (found.subject or None) if found is not None else None


def _subject_file(session: Path) -> Path | None:
    """SESSION/subjects/SUBJECT.json of the session's subject (None: it names none)."""
    subject = session_subject(session)
    return session / "subjects" / f"{subject}.json" if subject else None


def _calibration(calib: Path) -> tuple[CameraRig, dict]:
    if not calib.exists():
        raise AnnotateError(f"{calib}: no such calibration (give the calibration folder or its cameras.json)")
    rig = load_cameras(calib)
    file = calib / "cameras.json" if calib.is_dir() else calib
    return rig, {"calibration": str(calib), "calibration_sha256": file_sha256(file) if file.is_file() else ""}


def _bones_input(take: Take, bones: str | Path | np.ndarray | None) -> dict:
    """The bone lengths a take's annotation depends on, as known before the run: given, the
    session's subject file (their lengths' hash), or "estimated" by the run itself."""
    if bones is not None:
        lengths = load_subject(bones).bone_lengths if isinstance(bones, (str, Path)) else bones
        return {"bones": "given", "bones_sha256": array_sha256(np.asarray(lengths, np.float64))}
    file = _subject_file(take.path.resolve().parent)
    if file is None or not file.is_file():
        return {"bones": "estimated"}
    return {"bones": "subject file", "bones_sha256": array_sha256(load_subject(file).bone_lengths)}


def annotate_inputs(take: Take, cameras: Sequence[str], calibration: dict, options: AnnotateOptions,
                    bones: str | Path | np.ndarray | None = None, groups: Groups | None = None) -> dict:
    """Everything a take's annotation is made from (manus_core.provenance): it is reused only
    when these are the same."""
    mode = keypoint_mode(take, options)
    inputs: dict = {"cameras": list(cameras), "calibration_sha256": calibration["calibration_sha256"],
                    "keypoint_source": mode, "settings": options.settings, **_bones_input(take, bones)}
    if mode == "file" and (take.path / "keypoints2d.h5").is_file():
        inputs["keypoints_file_sha256"] = file_sha256(take.path / "keypoints2d.h5")
    elif mode == "detect":
        inputs["keypoint_model"] = options.model
        if options.palm_tiles:
            inputs["palm_tiles"] = True
    elif mode == "simulated":
        inputs["keypoint_simulation"] = {"noise_px": options.sim_noise_px, "outlier_rate": options.sim_outlier_rate,
                                         "dropout_rate": options.sim_dropout_rate, "seed": options.sim_seed}
    if cross_view_model(take, options) is not None:
        inputs["cross_view"] = True
    if groups is not None:
        inputs.update(frame_groups="given", frame_groups_sha256=array_sha256(*map(np.int64, groups)))
    elif (take.path / GROUPS_FILE).is_file():
        inputs.update(frame_groups="sync report", frame_groups_sha256=file_sha256(take.path / GROUPS_FILE))
    else:
        inputs["frame_groups"] = "computed"
    return stage_inputs(take, **inputs)


@dataclass
class AnnotateSummary:
    """`annotated`: takes computed now (`redone`: those replacing an earlier annotation, and why);
    `resumed`: kept from before (all inputs the same); `left_out`: cameras per take not used."""

    output: Path
    annotated: list[str] = field(default_factory=list)
    resumed: list[str] = field(default_factory=list)
    redone: dict[str, list[str]] = field(default_factory=dict)
    left_out: dict[str, list[str]] = field(default_factory=dict)
    failed: dict[str, str] = field(default_factory=dict)
    frames: int = 0
    frames_fitted: int = 0
    subjects: dict[str, str] = field(default_factory=dict)


def _take_key(task: TakeTask) -> str:
    return f"annotate-{task.key}"


def annotate(takes: Iterable[str | Path], calib: str | Path, output: str | Path,
             options: AnnotateOptions = AnnotateOptions(), *, workers: int = 1, scheduler: str | None = None,
             force: bool = False, bones: str | Path | np.ndarray | None = None,
             groups: Mapping[str, Groups] | Callable[[Take], Groups] | None = None,
             cameras: Sequence[str] | None = None, progress: Progress = silent) -> AnnotateSummary:
    """Annotate takes into DATASET.h5 (see the module doc). Returns what was done.

    groups: frame groups per take (a mapping from the take's path or key, or a function of the
    Take); takes without get the groups saved with their sync report, or the same grouping
    computed now when they have none (dataset_tools.sync.frame_groups). cameras: the cameras to
    use (default: every camera of a take that the calibration has). force: redo every take even
    when its inputs are the same. progress("annotate", takes done, takes) after each take, those
    kept from before first. Takes that fail are listed in the summary's `failed`; the others are
    written. Other stages' results in the output (masks, paint, contacts) are never touched.
    """
    calib = Path(calib)
    rig, calibration = _calibration(calib)
    opened = [Take(path) for path in takes]
    used = [cameras_used(take, rig.ids, calib, cameras) for take in opened]
    keys = [take_key(t.path) for t in opened]
    if len(set(keys)) != len(keys):
        raise AnnotateError(f"the same take is given twice: {sorted(k for k in keys if keys.count(k) > 1)[0]}")
    writer = DatasetWriter(output, force=force)
    summary = AnnotateSummary(Path(output))

    given = {k: groups(t) if callable(groups) else groups.get(str(t.path), groups.get(k)) if groups else None
             for t, k in zip(opened, keys)}

    def make_task(take: Take, key: str, bone_lengths=None, source="take", keypoints=None) -> TakeTask:
        cams = used[keys.index(key)]
        return TakeTask(str(take.path), key, rig.subset(cams), options, calibration, cams,
                        annotate_inputs(take, cams, calibration, options, bones, given[key]),
                        None if bone_lengths is None else np.asarray(bone_lengths, np.float64), source, given[key],
                        keypoints)

    todo, done = [], writer.done
    for take, key, cams in zip(opened, keys, used):
        if len(cams) < len(take.cameras):
            summary.left_out[key] = [c for c in take.cameras if c not in cams]
        if key in done:
            reasons = ["--force"] if force else differences(
                writer.inputs(key), annotate_inputs(take, cams, calibration, options, bones, given[key]))
            if not reasons:
                summary.resumed.append(key)
                continue
            summary.redone[key] = reasons
        todo.append((take, key))
    finished = len(summary.resumed)
    progress("annotate", finished, len(keys))
    found: dict[str, tuple] = {}    # the hand takes' keypoints, found for the bones
    session_bones = _session_bones(todo, list(zip(opened, keys)), bones, make_task, workers, scheduler, summary, found)
    # built after the session's bones: a subject file written by this run is what the takes depend on
    tasks = [make_task(t, k, *session_bones.get(t.path.resolve().parent, (None, "take")), found.get(k))
             for t, k in todo]
    for task, result in run_tasks(annotate_take, tasks, workers, scheduler, key=_take_key):
        if isinstance(result, KeyboardInterrupt):
            raise result
        if isinstance(result, BaseException):
            summary.failed[task.key] = str(result) if isinstance(result, ValueError) else repr(result)
        else:
            writer.add(result)
            summary.annotated.append(task.key)
            summary.frames += len(result.frame_ns)
            summary.frames_fitted += int(np.isfinite(result.joint_angles_raw[:, 0]).sum())
        finished += 1
        progress("annotate", finished, len(keys))
    if writer.saved:
        writer.finalize()
    return summary


def _session_bones(todo, every, bones, make_task, workers, scheduler, summary,
                   found: dict[str, tuple]) -> dict[Path, tuple[np.ndarray, str]]:
    """Bone lengths (and where they came from) per session folder of the takes to do, following the
    module doc; the hand takes among `every` take of the run count, also those done before. The hand
    takes' keypoints go into `found` by take key (TakeTask.keypoints)."""
    sessions = sorted({t.path.resolve().parent for t, _ in todo})
    if bones is not None:
        est = load_subject(bones) if isinstance(bones, (str, Path)) else None
        lengths = est.bone_lengths if est is not None else np.asarray(bones, np.float64)
        if lengths.shape != (20,):
            raise AnnotateError(f"bones: expected 20 lengths, got shape {lengths.shape}")
        return {s: (lengths, f"file:{bones}" if est is not None else "given") for s in sessions}
    out: dict[Path, tuple[np.ndarray, str]] = {}
    pending: dict[Path, list[TakeTask]] = {}
    for session in sessions:
        file = _subject_file(session)
        if file is not None and file.is_file():
            out[session] = (load_subject(file).bone_lengths, f"subject:{file.relative_to(session.parent)}")
            summary.subjects[session.name] = str(file)
            continue
        hand = [make_task(t, k) for t, k in every
                if t.path.resolve().parent == session and t.meta.get("kind") == "hand"]
        if hand:
            pending[session] = hand
    if not pending:
        return out
    samples: dict[Path, list[tuple[np.ndarray, float]]] = {s: [] for s in pending}
    tasks = [t for hand in pending.values() for t in hand]
    for task, result in run_tasks(hand_take_samples, tasks, workers, scheduler, key=_take_key):
        if isinstance(result, BaseException):
            raise AnnotateError(f"{task.path}: bone lengths of the subject: {result}") from None
        samples[Path(task.path).resolve().parent].append(result[:2])
        found[task.key] = result[2]
    for session, arrays in samples.items():
        est = bone_lengths_from_samples(np.concatenate([a for a, _ in arrays]),
                                        max(thr for _, thr in arrays))
        names = [Path(t.path).name for t in pending[session]]
        file = _subject_file(session)
        source = f"hand takes: {', '.join(names)}"
        if file is not None:
            file = save_subject(file, file.stem, est, names, software_version())
            summary.subjects[session.name] = str(file)
            source = f"subject:{file.relative_to(session.parent)} (from {', '.join(names)})"
        out[session] = (est.bone_lengths, source)
    return out
