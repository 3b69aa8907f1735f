"""Bone lengths of a subject from triangulated joints, and the subject file they are kept in.

    est = estimate_bone_lengths(joints3d, error_px)         # (T,21,3), (T,21) of the hand take(s)
    skeleton = est.skeleton()                               # HandSkeleton with the subject's bones
    save_subject(SESSION / "subjects" / "s01.json", "s01", est, takes=["hand_01"])
    lengths = load_subject(path).bone_lengths

Every frame gives one sample per bone: the distance between its two joints, where both were
triangulated and neither's reprojection error is high (above `max_error_px`, by default 2x the
median error of the take, at least 1 px). The length is a robust average of the samples: the
mean of the central 60% (`trim` = 0.2 off each end; `method="median"` for the plain median).
Poses do not matter: a bone's length is the same in every pose, so a hand take that moves through
many poses just gives many samples.

A bone with fewer than `min_samples` samples is not measured; it gets the default skeleton's length
scaled by the median ratio of measured to default lengths (the skeleton rescaled to the subject),
and is listed as `estimated`. With no bone measured at all, BoneLengthError says so.

Subject file (JSON, `SESSION/subjects/SUBJECT.json`, see docs/annotate.md):
    {"version": 1, "subject": "s01", "units": "m", "bone_names": [20 x "wrist-thumb_cmc", ...],
     "bone_lengths": [20], "spread_m": [20] (median absolute deviation of the samples),
     "samples": [20], "estimated": [bone names filled from the scaled default], "scale": ratio,
     "method": "trimmed-mean 0.2", "max_error_px": threshold used, "takes": [...], "software": "..."}
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import AfterValidator, Field

from manus_core.errors import BoneLengthError
from manus_core.fileio import write_atomic
from manus_core.skeleton import BONES, DEFAULT_BONE_LENGTHS, JOINT_NAMES, HandSkeleton
from manus_core.validation import Float, Int, Str, validate, worded

BONE_NAMES = tuple(f"{JOINT_NAMES[a]}-{JOINT_NAMES[b]}" for a, b in BONES)
SUBJECT_FORMAT_VERSION = 1
PerBone = Field(min_length=len(BONES), max_length=len(BONES))


@dataclass
class BoneLengths:
    """The subject's 20 bone lengths (m) with the evidence behind them."""

    bone_lengths: np.ndarray
    spread_m: np.ndarray
    samples: np.ndarray
    estimated: tuple[str, ...] = ()
    scale: float = 1.0
    method: str = "trimmed-mean 0.2"
    max_error_px: float = float("nan")
    takes: list[str] = field(default_factory=list)

    def skeleton(self, lower: np.ndarray | None = None, upper: np.ndarray | None = None) -> HandSkeleton:
        return HandSkeleton(self.bone_lengths, lower, upper)


def bone_samples(joints3d: np.ndarray, error_px: np.ndarray | None = None,
                 max_error_px: float | None = None) -> tuple[np.ndarray, float]:
    """Per-frame bone lengths (T,20), NaN where a joint is missing or its error too high, and the
    error threshold used."""
    X = np.asarray(joints3d, dtype=np.float64)
    if X.ndim != 3 or X.shape[1:] != (21, 3):
        raise BoneLengthError(f"bone lengths: joints3d must be (T, 21, 3), got shape {X.shape}")
    lengths = np.linalg.norm(X[:, BONES[:, 1]] - X[:, BONES[:, 0]], axis=-1)
    threshold = float("nan")
    if error_px is not None:
        err = np.asarray(error_px, dtype=np.float64)
        if err.shape != X.shape[:2]:
            raise BoneLengthError(f"bone lengths: error_px has shape {err.shape}, expected {X.shape[:2]}")
        finite = err[np.isfinite(err)]
        if max_error_px is None:
            max_error_px = max(2.0 * float(np.median(finite)), 1.0) if len(finite) else np.inf
        threshold = float(max_error_px)
        with np.errstate(invalid="ignore"):
            bad = ~(err <= threshold)
        lengths[bad[:, BONES[:, 0]] | bad[:, BONES[:, 1]]] = np.nan
    return lengths, threshold


def _trimmed_mean(x: np.ndarray, trim: float) -> np.ndarray:
    """Mean of the central (1 - 2 trim) of each column, NaN ignored (sorting puts NaN last)."""
    s = np.sort(x, axis=0)
    n = np.isfinite(x).sum(0)
    lo = np.floor(n * trim).astype(np.int64)
    hi = np.maximum(n - lo, lo + 1)
    rank = np.arange(len(x))[:, None]
    inside = (rank >= lo) & (rank < hi) & np.isfinite(s)
    with np.errstate(invalid="ignore"):
        return np.where(inside, s, 0.0).sum(0) / inside.sum(0)


def estimate_bone_lengths(joints3d: np.ndarray | Sequence[np.ndarray], error_px=None, *,
                          max_error_px: float | None = None, method: str = "trimmed", trim: float = 0.2,
                          min_samples: int = 10, reference: np.ndarray | None = None) -> BoneLengths:
    """Robust bone lengths from triangulated joints of one or more takes.

    joints3d: (T,21,3), or a list of them (one per take); error_px likewise (T,21) (None: every
    triangulated joint counts). See the module doc for the thresholds and the fallback.
    """
    takes = list(joints3d) if isinstance(joints3d, (list, tuple)) else [joints3d]
    errors = list(error_px) if isinstance(error_px, (list, tuple)) else [error_px] * len(takes)
    if len(errors) != len(takes):
        raise BoneLengthError(f"bone lengths: {len(takes)} joint arrays but {len(errors)} error arrays")
    parts = [bone_samples(j, e, max_error_px) for j, e in zip(takes, errors)]
    thresholds = [p[1] for p in parts if np.isfinite(p[1])]
    return bone_lengths_from_samples(np.concatenate([p[0] for p in parts]),
                                     max(thresholds) if thresholds else float("nan"), method=method, trim=trim,
                                     min_samples=min_samples, reference=reference)


def bone_lengths_from_samples(samples: np.ndarray, max_error_px: float = float("nan"), *, method: str = "trimmed",
                              trim: float = 0.2, min_samples: int = 10,
                              reference: np.ndarray | None = None) -> BoneLengths:
    """The robust average of per-frame bone lengths (N,20) (NaN = no sample), with the fallback
    of the module doc; max_error_px is only recorded."""
    if method not in ("trimmed", "median"):
        raise BoneLengthError(f"bone lengths: method = {method!r}; use 'trimmed' or 'median'")
    if not 0 <= trim < 0.5:
        raise BoneLengthError(f"bone lengths: trim = {trim} must be in [0, 0.5)")
    samples = np.asarray(samples, dtype=np.float64).reshape(-1, 20)
    count = np.isfinite(samples).sum(0)
    measured = count >= min_samples
    if not measured.any():
        raise BoneLengthError(f"bone lengths: no bone has {min_samples} good samples "
                              f"(most: {int(count.max())}); is there a hand in the take?")
    with np.errstate(invalid="ignore"):
        median = np.nanmedian(np.where(measured, samples, 0.0), axis=0)
        center = median if method == "median" else _trimmed_mean(samples, trim)
        spread = np.nanmedian(np.where(measured, np.abs(samples - median), 0.0), axis=0)
    ref = np.asarray(DEFAULT_BONE_LENGTHS if reference is None else reference, dtype=np.float64)
    scale = float(np.median(center[measured] / ref[measured]))
    lengths = np.where(measured, center, ref * scale)
    return BoneLengths(lengths, np.where(measured, spread, np.nan), count,
                       tuple(BONE_NAMES[b] for b in np.flatnonzero(~measured)), scale,
                       "median" if method == "median" else f"trimmed-mean {trim:g}", float(max_error_px))


def save_subject(path: str | Path, subject: str, bones: BoneLengths, takes: Sequence[str] = (),
                 software: str = "") -> Path:
    """Write the subject file (JSON, atomically)."""
    path = Path(path)
    doc = {"version": SUBJECT_FORMAT_VERSION, "subject": subject, "units": "m", "bone_names": list(BONE_NAMES),
           "bone_lengths": [float(x) for x in bones.bone_lengths],
           "spread_m": [None if not np.isfinite(x) else float(x) for x in bones.spread_m],
           "samples": [int(x) for x in bones.samples], "estimated": list(bones.estimated),
           "scale": bones.scale, "method": bones.method,
           "max_error_px": None if not np.isfinite(bones.max_error_px) else bones.max_error_px,
           "takes": [str(t) for t in (takes or bones.takes)], "software": software}
    write_atomic(path, (json.dumps(doc, indent=1) + "\n").encode())
    return path


# A bone of a human hand, a child's to a large adult's, is 5 mm to 15 cm long; a length of 45 is
# a file in millimetres.
BONE_RANGE_M = (0.005, 0.15)


def _in_order(names: tuple[str, ...]) -> tuple[str, ...]:
    if names != BONE_NAMES:
        raise ValueError("other bones or another order")
    return names


@dataclass(frozen=True)
class _SubjectFile:
    """A subject file as written (subject and software are not read back)."""

    version: Annotated[Literal[SUBJECT_FORMAT_VERSION],
                       worded(f"is {{value}}, this software reads {SUBJECT_FORMAT_VERSION}")]
    bone_lengths: Annotated[tuple[Annotated[Float, Field(ge=BONE_RANGE_M[0], le=BONE_RANGE_M[1])], ...], PerBone,
                            worded(f"must be {len(BONES)} positive lengths in metres, each in "
                                   f"[{BONE_RANGE_M[0]:g}, {BONE_RANGE_M[1]:g}], got {{value}}")]
    units: Annotated[Literal["m"], worded("is {value}; the lengths must be in metres ('m')")] = "m"
    # the lengths are in this order; a file with other bones (or another order) cannot be used
    bone_names: Annotated[tuple[Str, ...], AfterValidator(_in_order),
                          worded(f"must list the {len(BONES)} bones in the order {BONE_NAMES[0]} ... "
                                 f"{BONE_NAMES[-1]}, got {{value}}")] = BONE_NAMES
    spread_m: Annotated[tuple[Annotated[Float, Field(ge=0)] | None, ...], PerBone] = (None,) * len(BONES)
    samples: Annotated[tuple[Annotated[Int, Field(ge=0)], ...], PerBone] = (0,) * len(BONES)
    estimated: tuple[Annotated[Literal[BONE_NAMES], worded("{value} is not a bone name (wrist-thumb_cmc ... "
                                                           "pinky_dip-pinky_tip)")], ...] = ()
    scale: Annotated[Float, Field(gt=0)] = 1.0
    method: Str = ""
    max_error_px: Float | None = None
    takes: tuple[Str, ...] = ()


def load_subject(path: str | Path) -> BoneLengths:
    """Read a subject file; BoneLengthError names the file, the key and the problem."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise BoneLengthError(f"{path}: no such subject file") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise BoneLengthError(f"{path}: not valid JSON ({exc})") from None
    subject = validate(_SubjectFile, doc, str(path), BoneLengthError)
    return BoneLengths(np.array(subject.bone_lengths), np.array(subject.spread_m, dtype=np.float64),
                       np.array(subject.samples, dtype=np.int64), subject.estimated, subject.scale, subject.method,
                       float("nan") if subject.max_error_px is None else subject.max_error_px, list(subject.takes))
