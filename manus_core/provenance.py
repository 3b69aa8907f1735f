"""Which inputs made each stage's results in DATASET.h5, so that a result is reused only when
every input still matches (docs/annotate.md, "What is reused, and when").

    inputs = stage_inputs(take, calibration_sha256=..., keypoint_source="file", settings={...})
    group.attrs.update(provenance_attrs("annotate", inputs))           # stored with the results
    reasons = differences(read_provenance(group, "annotate"), inputs)  # [] = reuse them

A stage's inputs are a JSON object: "take" (the take's identity: its frame count per camera and
the SHA-256 of its frames.csv, so that a re-recorded take is never mistaken for the old one) and
whatever else the stage depends on (calibration hash, keypoint source, settings). Stages own
disjoint parts of a take group (STAGE_ARRAYS) and each keeps its own provenance attribute, so
that one stage redoing its part never touches another's.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from pathlib import Path

import h5py
import numpy as np

from manus_core.errors import TakeError
from manus_core.frames_csv import FILE_NAME as FRAMES_CSV
from manus_core.frames_csv import frames_csv_digest
from manus_core.take import Take

# The top-level names in a take group that each stage writes and replaces (and no other stage touches).
STAGE_ARRAYS: dict[str, tuple[str, ...]] = {
    "annotate": ("frame_ns", "frame_index", "keypoints2d", "keypoints3d", "keypoints3d_error_px",
                 "keypoints3d_views", "joint_angles_raw", "joint_angles", "bone_lengths", "ik_residual_m",
                 "flags"),
    "segment": ("masks", "paint"),
    "contacts": ("contacts",),
    "refine": ("joint_angles_refined", "refine"),
}


def take_identity(take: Take) -> dict:
    """{"frames": {cam: frames in frames.csv}, "frames_csv_sha256": hex}: what a recording is."""
    return {"frames": {cam: take.frame_count(cam) for cam in take.cameras},
            "frames_csv_sha256": frames_csv_digest(take.path / FRAMES_CSV)}


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a file an input was read from (a calibration, a keypoint file)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def array_sha256(*arrays: np.ndarray) -> str:
    """SHA-256 of arrays' values (given frame groups, bone lengths): equal arrays, equal hashes."""
    return hashlib.sha256(b"".join(np.ascontiguousarray(a).tobytes() for a in arrays)).hexdigest()


def cameras_used(take: Take, calibrated: Sequence[str], calibration: str | Path,
                 chosen: Sequence[str] | None = None) -> tuple[str, ...]:
    """The take's cameras a stage works on, in take.json order: those `chosen` (each must be in
    the take and in the calibration), else every camera of the take that the calibration has (a
    partial calibration leaves the others out); TakeError unless at least 2 remain."""
    meta = take.path / "take.json"
    if chosen:
        unknown = [c for c in chosen if c not in take.cameras]
        if unknown:
            raise TakeError(f"{meta}: --cameras names {', '.join(unknown)}, not cameras of the take "
                            f"({', '.join(take.cameras)})")
        uncalibrated = [c for c in chosen if c not in calibrated]
        if uncalibrated:
            raise TakeError(f"{calibration}: --cameras names {', '.join(uncalibrated)}, not in the calibration")
    used = tuple(c for c in take.cameras if c in (chosen or calibrated))
    if len(used) < 2:
        raise TakeError(f"{meta}: {len(used)} of the take's cameras ({', '.join(used) or 'none'}) "
                        f"{'chosen' if chosen else f'in the calibration {calibration}'}; 2 are needed")
    return used


def stage_inputs(take: Take, **inputs) -> dict:
    """The inputs of one stage's results for one take: {"take": take_identity(take), **inputs}.
    Values must be JSON-able (str, numbers, lists, dicts)."""
    return json.loads(json.dumps({"take": take_identity(take), **inputs}))


def _label(key: str) -> str:
    return key.removesuffix("_sha256").replace("_", " ")


def _take_differences(old: dict, new: dict) -> list[str]:
    old_frames, new_frames = old.get("frames", {}), new.get("frames", {})
    if list(old_frames) != list(new_frames):
        return [f"take re-recorded: cameras {','.join(old_frames) or 'none'} -> {','.join(new_frames)}"]
    changed = [f"frames of {cam} {old_frames[cam]} -> {n}" for cam, n in new_frames.items() if old_frames[cam] != n]
    if changed:
        return [f"take re-recorded: {', '.join(changed)}"]
    if old.get("frames_csv_sha256") != new.get("frames_csv_sha256"):
        return ["take re-recorded: frames.csv changed (same frame counts)"]
    return []


def _value(value) -> str:
    return "none" if value is None else json.dumps(value) if isinstance(value, (list, dict)) else str(value)


def _difference(key: str, before, value) -> list[str]:
    if key == "take":
        return _take_differences(before or {}, value)
    if key.endswith("_sha256"):
        return [f"{_label(key)} changed"]
    if isinstance(value, dict) and isinstance(before, dict):
        changed = [f"{k} {_value(before.get(k))} -> {_value(value.get(k))}"
                   for k in sorted(set(before) | set(value)) if before.get(k) != value.get(k)]
        return [f"{_label(key)}: {', '.join(changed)}"]
    return [f"{_label(key)} {_value(before)} -> {_value(value)}"]


def differences(old: dict | None, new: dict) -> list[str]:
    """Why results made from `old` inputs are not those `new` ones would make, one reason per
    input that differs ([] when all match). An input that only one side has (one that goes with
    another, such as the keypoint file's hash with the keypoint source) is named only when no
    shared input differs. None (results written before provenance was kept, or by another tool)
    never matches: nothing says what made them."""
    if old is None:
        return ["no record of the inputs that made it (written before provenance was kept)"]
    shared = [key for key in new if key in old]
    reasons = [r for key in shared if old[key] != new[key] for r in _difference(key, old[key], new[key])]
    if reasons:
        return reasons
    return ([r for key in new if key not in old for r in _difference(key, None, new[key])]
            + [f"{_label(key)} no longer an input" for key in old if key not in new])


def provenance_attrs(stage: str, inputs: dict) -> dict:
    """{f"provenance_{stage}": JSON of the inputs}: the take group attribute to write with the results."""
    return {f"provenance_{stage}": json.dumps(inputs, sort_keys=True)}


def read_provenance(group: h5py.Group, stage: str) -> dict | None:
    """The inputs that made `stage`'s results in this take group, None when none are recorded
    (or the record is not JSON)."""
    raw = group.attrs.get(f"provenance_{stage}")
    if raw is None:
        return None
    try:
        found = json.loads(raw.decode() if isinstance(raw, bytes) else str(raw))
    except json.JSONDecodeError:
        return None
    return found if isinstance(found, dict) else None
