"""Segmentation of recorded take folders into DATASET.h5 (the `segment` command's work)."""

from __future__ import annotations

import hashlib
import json
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from manus_core.cameras import CameraRig
from manus_core.dataset import add_arrays, read_dataset
from manus_core.errors import SegmentationError
from manus_core.fileio import write_atomic
from manus_core.progress import Progress, silent
from manus_core.provenance import differences, stage_inputs, take_identity
from manus_core.take import Take

from ..sync import frame_groups
from .colour import PaintKey
from .groups import GROUPS_PER_TASK, backgrounds_for, sample_frames, segment_in_tasks
from .paint import paint_masks
from .pngs import load_png_masks
from .store import MaskStore
from .views import object_colour, paint_key_from_object


@dataclass(frozen=True)
class Segmentation:
    """The masks of one take, cameras in take.json order.

    frame_ns (T,) and frame_index (T,C) (each camera's frame in each group, -1: none): the take's
    frame groups (every `every`-th); hand and object (T,C,H,W) bool; paint (C,H,W) bool for a
    canonical take with a paint colour, else None, segmented in group paint_group; report:
    warnings, the frame grouping used and paint statistics. With a `store` on disk, hand and object
    are its HDF5 datasets (they index like arrays) until close().
    """

    cameras: tuple[str, ...]
    frame_ns: np.ndarray
    frame_index: np.ndarray
    hand: np.ndarray
    object: np.ndarray
    paint: np.ndarray | None
    paint_group: int | None
    report: dict
    store: MaskStore | None = field(default=None, repr=False)

    def close(self) -> None:
        """Remove the masks' file, when they are in one (segment_take's `masks_file`)."""
        if self.store is not None:
            self.store.close()

    def in_order(self, ids: list[str] | tuple[str, ...]) -> list[int]:
        """Column of each camera of `ids` (e.g. a calibration's order) in these masks."""
        return [self.cameras.index(c) for c in ids]


def _object_frames(obj: Take, cameras, backgrounds) -> tuple[np.ndarray, list]:
    images, bgs = [], []
    for cam, bg in zip(cameras, backgrounds):
        if bg is not None and cam in obj.cameras and obj.frame_count(cam):
            frames = sample_frames(obj, cam, 2)
            images.extend(frames)
            bgs.extend([bg] * len(frames))
    if not images:
        raise SegmentationError(f"{obj.path}: no camera with a background to find the object in "
                                "(give the background take, or --swatch for the paint colour)")
    return np.stack(images), bgs


def take_cameras(take: Take, rig: CameraRig, wanted: Sequence[str] | None = None) -> list[str]:
    """The cameras of `take` to work on, in take.json order: `wanted`, or by default every camera
    of the take that the calibration has (a partial calibration, calibrate --allow-partial,
    leaves some out). A camera asked for by name must be in the take and calibrated, and at least
    two must remain; SegmentationError names the cameras otherwise."""
    if wanted is not None:
        unknown = [c for c in wanted if c not in take.cameras]
        if unknown:
            raise SegmentationError(f"{take.path}: no camera {', '.join(unknown)} in this take "
                                    f"(cameras: {', '.join(take.cameras)})")
    used = [c for c in take.cameras if c in rig.ids and (wanted is None or c in wanted)]
    uncalibrated = [c for c in wanted or () if c not in rig.ids]
    if uncalibrated:
        raise SegmentationError(f"{take.path}: cameras {', '.join(uncalibrated)} are not in the calibration")
    if len(used) < 2:
        raise SegmentationError(f"{take.path}: {len(used)} of its cameras ({', '.join(used) or 'none'}) in the "
                                f"calibration; masks need at least 2")
    return used


def segment_take(take_path: Path, rig: CameraRig, background_path: Path | None, object_path: Path | None = None,
                 swatch=None, every: int = 1, progress: Progress = silent,
                 masks: Path | None = None, cameras: Sequence[str] | None = None, workers: int = 1,
                 scheduler: str | None = None, groups_per_task: int = GROUPS_PER_TASK,
                 masks_file: Path | None = None) -> Segmentation:
    """Masks of a take: hand and object in every frame group, and in a canonical take the paint
    (its colour from the object take or `swatch` B,G,R). The groups are those of the take's sync
    report (as annotate's), every `every`-th; the paint is segmented in the middle group of a
    canonical take (the hand holds still there). progress ("segment", groups done, groups).
    cameras: those to segment (take_cameras; by default the take's calibrated cameras, and a
    warning names those a partial calibration leaves out). The groups' masks are computed in tasks
    of `groups_per_task` groups: inline, in `workers` local processes or on the Dask `scheduler`
    (dataset_tools.tasks.run_tasks), and written as they come into `masks_file` (an HDF5 file the
    caller removes with Segmentation.close(); a long take's masks need not fit in memory), or
    held in memory when it is None.

    With `masks`, a folder of masks made by another tool, the hand and object masks are read from
    MASKS/hand/CAM/FRAME.png and MASKS/object/CAM/FRAME.png (FRAME: the camera's frame index, 6
    digits; nonzero = foreground; without an object folder there is no object) instead of being
    segmented; the background take is then optional (it sharpens the paint's edges along the
    silhouette). Raises SegmentationError on input it cannot work with; what only lowers the
    quality is a warning in the report (and a Python warning)."""
    take = Take(take_path)
    kind = take.meta.get("kind")
    report: dict = {"warnings": []}
    cams = take_cameras(take, rig, cameras)
    uncalibrated = [c for c in take.cameras if c not in rig.ids]
    if uncalibrated:
        report["warnings"].append(f"cameras {', '.join(uncalibrated)} are not in the calibration: left out "
                                  f"(masks of {len(cams)} of {len(take.cameras)} cameras)")
    rig = rig.subset(cams)
    if background_path is not None:
        backgrounds = backgrounds_for(take, cams, Take(background_path), report)
    elif masks is not None:
        backgrounds = [None] * len(cams)
    else:
        raise SegmentationError(f"{take.path}: no background take (the empty cube) and no masks to use instead")
    model = key = None
    if object_path is not None:
        images, bgs = _object_frames(Take(object_path), cams, backgrounds)
        # a canonical take has no object in it, and the paint on its hand has the (painted)
        # object's colour: there every foreground pixel is hand; in the object take every one is
        # object (a colour split would give its skin-coloured shading to a hand that is not there)
        model = None if kind in ("canonical", "object") or masks is not None else object_colour(images, bgs)
        key = paint_key_from_object(images, bgs) if swatch is None else None
    if swatch is not None:
        key = PaintKey.from_swatch(swatch)
    groups = frame_groups(take)
    report["frame_groups"] = groups.description
    columns = [groups.cameras.index(c) for c in cams]
    frame_ns, frame_index = groups.frame_ns[::every], groups.frame_index[::every][:, columns]
    # a video cut short (a crash mid-take): its missing frames are views not captured
    report["warnings"].extend(take.missing_notes(cams))
    readable = np.array([take.readable_frames(cam) for cam in cams])
    frame_index = np.where(frame_index < readable, frame_index, -1)
    w, h = (int(v) for v in rig.size[0])
    store = MaskStore((len(frame_index), len(cams), h, w), masks_file)
    try:
        if masks is None:
            segment_in_tasks(take, rig, background_path, model, frame_index, store, workers, scheduler, progress,
                             groups_per_task)
        else:
            hand = load_png_masks(Path(masks) / "hand", cams, frame_index, (h, w))
            objects = Path(masks) / "object"
            store.put(0, hand, load_png_masks(objects, cams, frame_index, (h, w)) if objects.is_dir()
                      else np.zeros_like(hand))
            progress("segment", len(frame_index), len(frame_index))
        paint = middle = None
        if kind == "canonical" and key is None:
            report["warnings"].append("canonical take without --object-take or --swatch: no paint masks")
        elif kind == "canonical":
            middle = len(frame_ns) // 2
            images = np.stack([take.read_frame(cam, int(max(frame_index[middle, c], 0)))
                               for c, cam in enumerate(cams)])
            lit = [None if b is None else b.at_brightness(image) for b, image in zip(backgrounds, images)]
            paint, paint_report = paint_masks(images, store.hand[middle], key, backgrounds=lit)
            report["paint"] = paint_report
            report["warnings"].extend(paint_report["warnings"])
    except BaseException:
        store.close()
        raise
    for message in report["warnings"]:
        warnings.warn(message, stacklevel=2)
    return Segmentation(tuple(cams), frame_ns, frame_index, store.hand, store.object, paint, middle, report,
                        store if masks_file is not None else None)


def segment_inputs(take: Take, rig: CameraRig, cameras: Sequence[str], background: Path | None,
                   object_take: Path | None, swatch, every: int, masks: Path | None) -> dict:
    """What a take's masks are made from (manus_core.provenance): the take's recording, the
    calibration of the cameras used (whatever file it came from), the background and object
    takes' recordings, and the settings."""
    calibration = json.dumps(rig.subset(cameras).to_json(), sort_keys=True).encode()
    return stage_inputs(take, calibration_sha256=hashlib.sha256(calibration).hexdigest(), cameras=list(cameras),
                        background=_recording(background), object_take=_recording(object_take),
                        swatch=None if swatch is None else [float(v) for v in swatch], every=int(every),
                        masks=None if masks is None else str(Path(masks).resolve()))


def _recording(path: Path | None) -> str | None:
    """Another take an input is read from, as its folder and the start of its frames.csv hash."""
    if path is None:
        return None
    take = Take(path)
    return f"{take.path.resolve()} (frames.csv {take_identity(take)['frames_csv_sha256'][:12]})"


def stale_masks(path: Path, key: str, inputs: dict) -> list[str] | None:
    """Why take `key`'s masks in DATASET.h5 are not those `inputs` make ([]: they are current;
    None: the take has no masks there). Checked before the work."""
    path = Path(path)
    if not path.exists():
        return None
    dataset = read_dataset(path)
    if key not in dataset or "segment" not in dataset.stages(key):
        return None
    return differences(dataset.provenance(key, "segment"), inputs)


def write_masks(path: Path, key: str, result: Segmentation, attrs: dict,
                arrays: dict[str, np.ndarray] | None = None) -> None:
    """Add masks/hand, masks/object, masks/frame_ns (and paint/masks, and the other `arrays` of
    segment's part, e.g. paint/contact) to take `key` of DATASET.h5, atomically, in one write
    (dataset.add_arrays; no other stage's arrays are touched). The masks' own frame groups are
    stored: with --every they are a subset of the annotation's."""
    out = {"masks/hand": result.hand, "masks/object": result.object, "masks/frame_ns": result.frame_ns}
    if result.paint is not None:
        out["paint/masks"] = result.paint
    add_arrays(path, key, {**out, **(arrays or {})}, {"mask_cameras": list(result.cameras), **attrs}, stage="segment")


def write_overlays(folder: Path, take: Take, result: Segmentation, t: int | None = None) -> list[Path]:
    """PNG overlays FOLDER/CAM.png of group t (hand red, object blue, paint green) for a quick look;
    by default the group the paint was segmented in, else the first."""
    if t is None:
        t = result.paint_group or 0
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for c, cam in enumerate(result.cameras):
        k = int(result.frame_index[t, c])
        if k < 0:
            continue
        image = take.read_frame(cam, k).astype(np.float32)
        tint = np.zeros_like(image)
        tint[result.hand[t, c]] = (0, 0, 255)
        tint[result.object[t, c]] = (255, 0, 0)
        if result.paint is not None:
            tint[result.paint[c]] = (0, 255, 0)
        shown = np.where(tint.any(axis=-1, keepdims=True), 0.5 * image + 0.5 * tint, image)
        target = folder / f"{cam}.png"
        ok, buf = cv2.imencode(".png", shown.astype(np.uint8))
        if ok:
            write_atomic(target, buf.tobytes())
            out.append(target)
    return out
