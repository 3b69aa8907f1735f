"""Training views from recorded takes: what `reconstruct object|hand` and the demo feed the trainers.

A take stores distorted MJPEG frames per camera (manus_core.take.Take). The views the
trainers want are undistorted float images with pinhole intrinsics, optionally reduced
(`scale`). For training they are best cut to windows around the subject (`crop_views`): the
object covers a few percent of a cube camera's image, and every pixel outside the window would
cost rendering time and teach nothing but the background colour. All views of one set share one
window size (the rasterizer renders a batch at one size); each window sits around its own view's
mask, and the intrinsics' principal point moves with it. Evaluate on the whole views.

Masks: arrays given by the caller (e.g. from dataset_tools.segmentation), or "truth": the
per-pixel labels of a simulated take's ground_truth.h5 (2 = object; 1 and 3 = hand and paint on
it). Labels exist for the ticks the recording asked for; a simulated camera's frame with
sequence number s was exposed at tick s (free-run and hardware-trigger rigs), which is how
frames find their labels and their true joint angles.

Views in which the subject is hidden are left out: for the object, views whose mask is smaller
than `min_mask_fraction` of the largest (the table hides the object from cameras below its top);
for the hand, views in which fewer than 90 % of the joints that project into the image land on
the mask (the hand is occluded there, and a mask that cuts it would teach the model holes).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import h5py
import numpy as np
import torch

from dataset_tools.segmentation.background import BackgroundModel
from dataset_tools.segmentation.groups import sample_frames
from manus_core.cameras import CameraRig, scale_intrinsics
from manus_core.dataset import Dataset, read_dataset
from manus_core.errors import TakeInputError
from manus_core.ground_truth import FILE_NAME as GROUND_TRUTH
from manus_core.ground_truth import GroundTruth, TruthHand
from manus_core.skeleton import HandSkeleton
from manus_core.take import Take

from .trainer import Views

OBJECT_LABELS = (2,)
HAND_LABELS = (1, 3)
JOINTS_ON_MASK = 0.9


# --- ground truth of simulated takes -----------------------------------------------------------

def _truth_path(take_path: str | os.PathLike) -> Path:
    path = Path(take_path) / GROUND_TRUTH
    if not path.is_file():
        raise TakeInputError(f"{path}: missing (only simulated takes have ground truth)")
    return path


def truth_cameras(take_path: str | os.PathLike) -> CameraRig:
    """The exact cameras of a simulated take (ground_truth.h5 `cameras/...`)."""
    return GroundTruth(_truth_path(take_path)).cameras.rig()


def truth_labels(take_path: str | os.PathLike, cameras: Sequence[str], seqs: np.ndarray) -> np.ndarray:
    """Per-pixel labels (T,C,H,W) uint8 of the frames with sequence numbers seqs (T,C) (-1: none,
    left 0) from a simulated take's ground truth; TakeInputError when a frame has no labels."""
    path = _truth_path(take_path)
    seqs = np.asarray(seqs)
    gt = GroundTruth(path)
    gt_ids = list(gt.cameras.ids)
    labelled = {int(t): j for j, t in enumerate(gt.label_frames)}
    missing = sorted({int(t) for t in seqs[seqs >= 0]} - labelled.keys())
    if missing:
        raise TakeInputError(f"{path}: no labels for tick {missing[0]} (labelled ticks: "
                             f"{', '.join(map(str, sorted(labelled))) or 'none'})")
    out = np.zeros((seqs.shape[0], len(cameras)) + gt.label_size, np.uint8)
    for c, cam in enumerate(cameras):
        if cam not in gt_ids:
            raise TakeInputError(f"{path}: no camera {cam!r} in the ground truth")
        rows = np.flatnonzero(seqs[:, c] >= 0)
        out[rows, c] = gt.label_images([gt_ids.index(cam)] * len(rows), [labelled[int(t)] for t in seqs[rows, c]])
    return out


# --- frames of a take ----------------------------------------------------------------------------

def frames_with_seq(take: Take, cameras: Sequence[str], seqs: Sequence[int]) -> np.ndarray:
    """Frame indices (T,C) of the frames whose sequence number is seqs[t] (-1 where a camera has
    none, e.g. a dropped frame)."""
    out = np.full((len(seqs), len(cameras)), -1, np.int64)
    want = np.asarray(seqs, np.int64)
    for c, cam in enumerate(cameras):
        seq = take.camera_frames(cam)["seq"]
        order = np.argsort(seq, kind="stable")
        pos = np.searchsorted(seq[order], want).clip(0, max(len(seq) - 1, 0))
        if len(seq):
            hit = seq[order][pos] == want
            out[hit, c] = order[pos[hit]]
    return out


def _seq_of(take: Take, cameras: Sequence[str], index: np.ndarray) -> np.ndarray:
    """Sequence numbers (T,C) of frame indices (T,C) (-1 stays -1)."""
    out = np.full(index.shape, -1, np.int64)
    for c, cam in enumerate(cameras):
        seq = take.camera_frames(cam)["seq"]
        ok = (index[:, c] >= 0) & (index[:, c] < len(seq))
        out[ok, c] = seq[index[ok, c]]
    return out


# --- views ---------------------------------------------------------------------------------------

def undistort(rig: CameraRig, images: Sequence[np.ndarray], masks: Sequence[np.ndarray] | None,
              scale: float = 1.0) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Undistort and reduce: (images (V,H,W,3) float32 RGB in [0,1], masks (V,H,W) bool | None,
    K (V,3,3)) for BGR uint8 images of the rig's cameras, in rig order."""
    out_images, out_masks, Ks = [], [], []
    for i, image in enumerate(images):
        K, dist = rig.K[i], rig.dist[i]
        w, h = int(rig.size[i, 0]), int(rig.size[i, 1])
        if image.shape[:2] != (h, w):
            raise TakeInputError(f"camera {rig.ids[i]}: image is {image.shape[1]}x{image.shape[0]}, "
                                 f"the calibration says {w}x{h}")
        size = (max(int(round(w * scale)), 1), max(int(round(h * scale)), 1))
        sx, sy = size[0] / w, size[1] / h
        Ks.append(scale_intrinsics(K, sx, sy))
        plain = cv2.undistort(image, K, dist)
        out_images.append(cv2.resize(plain, size, interpolation=cv2.INTER_AREA)[..., ::-1] / np.float32(255))
        if masks is not None:
            m = cv2.undistort((np.asarray(masks[i]) > 0).astype(np.float32), K, dist)
            out_masks.append(cv2.resize(m, size, interpolation=cv2.INTER_AREA) > 0.5)
    sizes = {im.shape[:2] for im in out_images}
    if len(sizes) > 1:
        raise TakeInputError(f"the cameras' image sizes differ after scaling ({sorted(sizes)}); "
                             "train cameras of one resolution together")
    return (np.stack(out_images).astype(np.float32), None if masks is None else np.stack(out_masks),
            np.stack(Ks))


def crop_to_masks(images: np.ndarray, masks: np.ndarray, Ks: np.ndarray, margin: int,
                  multiple: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cut every view to a window of one common size around its mask's bounding box.

    The size is the largest box plus `margin` pixels on each side, rounded up to `multiple`
    (the rasterizer's tile) and at most the image; each window is centred on its box and kept
    inside the image. Returns the cropped images, masks and shifted intrinsics.
    """
    V, H, W = masks.shape
    ys, xs = masks.any(2), masks.any(1)
    has = xs.any(1)
    # x0, y0, x1, y1 inclusive; an empty mask gets an empty box at the origin
    boxes = np.stack([xs.argmax(1), ys.argmax(1), W - 1 - xs[:, ::-1].argmax(1), H - 1 - ys[:, ::-1].argmax(1)], 1)
    boxes = np.where(has[:, None], boxes, 0)
    need_w = int((boxes[:, 2] - boxes[:, 0]).max()) + 1 + 2 * margin
    need_h = int((boxes[:, 3] - boxes[:, 1]).max()) + 1 + 2 * margin
    cw, ch = min(-(-need_w // multiple) * multiple, W), min(-(-need_h // multiple) * multiple, H)
    x0 = np.clip((boxes[:, 0] + boxes[:, 2] + 1) // 2 - cw // 2, 0, W - cw)
    y0 = np.clip((boxes[:, 1] + boxes[:, 3] + 1) // 2 - ch // 2, 0, H - ch)
    rows = y0[:, None] + np.arange(ch)[None]
    cols = x0[:, None] + np.arange(cw)[None]
    v = np.arange(V)[:, None, None]
    K = Ks.copy()
    K[:, 0, 2] -= x0
    K[:, 1, 2] -= y0
    return images[v, rows[:, :, None], cols[:, None, :]], masks[v, rows[:, :, None], cols[:, None, :]], K


def crop_views(views: Views, margin: int = 8) -> Views:
    """The views cut to windows around their masks (crop_to_masks): what to train on. Views
    without masks are returned as they are."""
    if views.masks is None or not bool(views.masks.any()):
        return views
    # the backgrounds ride along as three more channels, cut with the same windows
    pixels = views.images if views.backgrounds is None else torch.cat([views.images, views.backgrounds], -1)
    pixels, masks, Ks = crop_to_masks(pixels.cpu().numpy(), views.masks.cpu().numpy(),
                                      views.Ks.cpu().double().numpy(), margin)
    device = views.images.device
    pixels = torch.as_tensor(pixels, device=device)
    return Views(pixels[..., :3], torch.as_tensor(Ks, dtype=torch.float32, device=device), views.viewmats,
                 torch.as_tensor(masks, device=device), views.ids,
                 None if views.backgrounds is None else pixels[..., 3:])


def empty_scene(take_path: str | os.PathLike, cameras: Sequence[str]) -> dict[str, np.ndarray]:
    """What each camera sees of the empty cube: the median (H,W,3) BGR float32 of a few frames
    of an empty take (segment's background model), per camera id. A camera it lacks is an error:
    models drawn over the empty cube in some views and over nothing in others score nothing."""
    take = Take(take_path)
    missing = [cam for cam in cameras if cam not in take.cameras or not take.frame_count(cam)]
    if missing:
        raise TakeInputError(f"{take.path}: the empty take has no frames of cameras {', '.join(missing)}")
    return {cam: BackgroundModel.fit(sample_frames(take, cam)).median for cam in cameras}


def _exposure(images: np.ndarray, backgrounds: np.ndarray, masks: np.ndarray | None) -> np.ndarray:
    """Each view's brightness (V,) relative to its background: the median ratio away from the
    (grown) mask. The cameras' exposure and the lights drift between takes."""
    ratio = images.mean(-1) / np.maximum(backgrounds.mean(-1), 1 / 64)
    if masks is not None:
        grown = np.stack([cv2.dilate(m.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0 for m in masks])
        ratio = np.where(grown, np.nan, ratio)
    return np.nan_to_num(np.nanmedian(ratio.reshape(len(ratio), -1), axis=1), nan=1.0).astype(np.float32)


def _views(rig: CameraRig, images, masks, scale: float, behind: dict[str, np.ndarray] | None = None) -> Views:
    """Views of rig's cameras; with `behind` (empty_scene), their backgrounds too, brought to each
    view's exposure."""
    imgs, msk, Ks = undistort(rig, images, masks, scale)
    backgrounds = None
    if behind is not None:
        backgrounds, _, _ = undistort(rig, [behind[c] for c in rig.ids], None, scale)
        backgrounds = torch.as_tensor(backgrounds * _exposure(imgs, backgrounds, msk)[:, None, None, None])
    return dataclasses.replace(Views.from_rig(imgs, Ks, rig.R, rig.t, msk, rig.ids), backgrounds=backgrounds)


def _open(take_path: str | os.PathLike, rig: CameraRig) -> Take:
    take = Take(take_path)
    missing = [c for c in rig.ids if c not in take.cameras]
    if missing:
        raise TakeInputError(f"{take.path}: no videos of cameras {', '.join(missing)}")
    return take


def object_views_from_take(take_path: str | os.PathLike, rig: CameraRig, frame: int | None = None,
                           masks: np.ndarray | str | None = "truth", scale: float = 1.0,
                           min_mask_fraction: float = 0.25, behind: dict[str, np.ndarray] | None = None) -> Views:
    """Views of a static object: one frame of every camera of `rig` (any subset of the take's).

    frame: each camera's frame index; None takes the first tick with labels when masks="truth",
    else frame 0. masks: "truth" (ground_truth.h5 labels), an array (C,H,W) bool in rig order at
    the cameras' resolution, or None (whole images, no crop). Views where the object is hidden
    (mask below min_mask_fraction of the largest) are left out; Views.ids names the kept cameras.
    behind: the empty scene (empty_scene) for the views' backgrounds.
    """
    take = _open(take_path, rig)
    if isinstance(masks, str) and masks != "truth":
        raise ValueError(f"masks must be an array, 'truth' or None, not {masks!r}")
    if frame is None and isinstance(masks, str):
        ticks = GroundTruth(_truth_path(take_path)).label_frames
        index = frames_with_seq(take, rig.ids, ticks)
        complete = np.flatnonzero((index >= 0).all(1))
        if not len(complete):
            raise TakeInputError(f"{take.path}: no labelled tick has a frame of every camera")
        index = index[complete[:1]]
    else:
        index = np.full((1, len(rig)), 0 if frame is None else int(frame), np.int64)
    images = [take.read_frames(cam, index[0, c:c + 1])[int(index[0, c])] for c, cam in enumerate(rig.ids)]
    if isinstance(masks, str):
        masks = np.isin(truth_labels(take_path, rig.ids, _seq_of(take, rig.ids, index))[0], OBJECT_LABELS)
    elif masks is not None:
        masks = np.asarray(masks, bool)
        if masks.shape[0] != len(rig):
            raise ValueError(f"masks has {masks.shape[0]} views for {len(rig)} cameras")
    keep = np.arange(len(rig))
    if masks is not None:
        area = masks.reshape(len(rig), -1).sum(1)
        keep = np.flatnonzero(area >= min_mask_fraction * max(area.max(), 1))
    sub = rig.subset([rig.ids[i] for i in keep])
    return _views(sub, [images[i] for i in keep], None if masks is None else masks[keep], scale, behind)


@dataclass
class HandFrames:
    """The frames of a hand take and their joint angles: the input of hand_views_from_take.

    angles (T,26) and bone_lengths (20,) of the skeleton; frame_index (T,C) each camera's frame
    index in the take (-1: none), cameras in that order; source names where the angles came from,
    key the take's SESSION/TAKE in DATASET.h5 when they came from there.
    """

    angles: np.ndarray
    bone_lengths: np.ndarray
    frame_index: np.ndarray
    cameras: tuple[str, ...]
    source: str
    key: str | None = None

    def __len__(self) -> int:
        return len(self.angles)


def hand_frames_from_truth(take_path: str | os.PathLike) -> HandFrames:
    """Every tick of a simulated hand take with its true joint angles and bone lengths."""
    path = _truth_path(take_path)
    gt = GroundTruth(path)
    if not gt.has(TruthHand):
        raise TakeInputError(f"{path}: no hand in this take's ground truth")
    angles, bones = gt.hand.joint_angles, gt.hand.bone_lengths
    take = Take(take_path)
    index = frames_with_seq(take, take.cameras, np.arange(len(angles)))
    return HandFrames(angles, bones, index, take.cameras, f"{path}")


def _dataset_take(dataset_path: str | os.PathLike, take_key: str | None, stage: str) -> tuple[Dataset, str]:
    """DATASET.h5 and the key of the take asked for; None: its only take with `stage`'s results."""
    ds = read_dataset(dataset_path)
    if take_key is None:
        having = [key for key in ds.takes if stage in ds.stages(key)]
        if len(having) != 1:
            raise TakeInputError(f"{dataset_path}: holds {len(having)} takes with {stage} results "
                                 f"({', '.join(having) or 'none'}); name one")
        return ds, having[0]
    if take_key not in ds:
        raise TakeInputError(f"{dataset_path}: no take {take_key!r} (takes: {', '.join(ds.takes) or 'none'})")
    return ds, take_key


def hand_frames_from_dataset(dataset_path: str | os.PathLike, take_key: str | None = None) -> HandFrames:
    """The frame groups of one take of DATASET.h5 with the pose each frame's own IK fit gave
    (`joint_angles_raw`; annotate's filtered `joint_angles` where the fit left a DOF undetermined)
    and annotate's bone lengths.

    A model is fitted to each frame's images, so each frame needs the pose its images show. The
    1-euro filter trades jitter for lag, and a hand take runs through its poses fast: there the
    filtered poses lag the images by millimetres (docs/splat.md, "Training poses").

    take_key "SESSION/TAKE"; None when the dataset holds one annotated take only. A take without
    annotation is refused (DatasetError names it and the stages it has).
    """
    ds, take_key = _dataset_take(dataset_path, take_key, "annotate")
    ann = ds[take_key]
    own = np.isfinite(ann.joint_angles_raw).all(axis=1)
    angles = np.where(own[:, None], ann.joint_angles_raw, ann.joint_angles)
    return HandFrames(angles, ann.bone_lengths, ann.frame_index, ann.cameras,
                      f"{dataset_path}:{take_key}", take_key)


def mask_cameras(dataset_path: str | os.PathLike, take_key: str | None) -> list[str]:
    """The cameras whose hand masks `segment` stored for a take of DATASET.h5; refused when the
    take has no masks, or when they are of another recording than its annotation."""
    ds, key = _dataset_take(dataset_path, take_key, "segment")
    with h5py.File(dataset_path, "r") as f:
        group = f[key]
        if "masks/hand" not in group:
            raise TakeInputError(f"{dataset_path}: take {key} has no hand masks (run `manus-capture segment` on it)")
        cameras = [c.decode() if isinstance(c, bytes) else str(c) for c in group.attrs["mask_cameras"]]
    other = ds.recording_differences(key, "segment")
    if other:
        raise TakeInputError(f"{dataset_path}: take {key}: its masks and its annotation are of different recordings "
                             f"({'; '.join(other)}); redo whichever ran before the take was recorded again")
    return cameras


def hand_masks_from_dataset(dataset_path: str | os.PathLike, take_key: str | None, rows: Sequence[int],
                            cameras: Sequence[str]) -> np.ndarray:
    """Hand masks (P,C,H,W) that `segment` stored for a take (masks/hand), for annotation rows
    `rows` of that take (matched on frame_ns) and `cameras` in that order."""
    ds, key = _dataset_take(dataset_path, take_key, "annotate")
    frame_ns = ds[key].frame_ns[np.asarray(rows, np.int64)]
    mask_cams = mask_cameras(dataset_path, key)
    missing = [c for c in cameras if c not in mask_cams]
    if missing:
        raise TakeInputError(f"{dataset_path}: take {key} has no masks of cameras {', '.join(missing)}")
    with h5py.File(dataset_path, "r") as f:
        group = f[key]
        mask_ns = group["masks/frame_ns"][()]
        lookup = {int(t): i for i, t in enumerate(mask_ns)}
        absent = [int(t) for t in frame_ns if int(t) not in lookup]
        if absent:
            raise TakeInputError(f"{dataset_path}: take {key} has no masks for {len(absent)} of the chosen frame "
                                 "groups (segment it with --every 1)")
        index = [lookup[int(t)] for t in frame_ns]
        order = [mask_cams.index(c) for c in cameras]
        masks = group["masks/hand"]
        return np.stack([masks[i][order] for i in index])


def spread_frames(angles: np.ndarray, count: int) -> np.ndarray:
    """Up to `count` frames with a fitted hand (no NaN angle), spread evenly over the take. Fitted
    angles carry the detector's noise and are never still to still_frames' tolerance; with cameras
    triggered together any frame group shows one pose in every view."""
    fitted = np.flatnonzero(np.isfinite(np.asarray(angles, np.float64)).all(axis=1))
    if not len(fitted):
        return fitted
    return fitted[np.unique(np.linspace(0, len(fitted) - 1, count).round().astype(int))]


def still_frames(angles: np.ndarray, tolerance: float = 1e-3, count: int | None = None) -> np.ndarray:
    """The middle frame of every run of frames in which the hand holds still.

    A frame is still when no joint angle (radians) or translation (metres) differs from the next
    frame's by more than `tolerance`; NaN frames (no hand) are never still. A hold is where the
    images of all cameras show the pose the angles say, whatever their exposure times. With
    `count`, that many of them, spread evenly.
    """
    a = np.asarray(angles, np.float64)
    step = np.abs(np.diff(a, axis=0)).max(1)
    still = np.zeros(len(a), bool)
    still[:-1] |= step <= tolerance
    still[1:] |= step <= tolerance
    still &= np.isfinite(a).all(1)
    edges = np.diff(np.concatenate([[0], still.astype(np.int8), [0]]))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    middle = (starts + stops - 1) // 2
    if count is not None and count < len(middle):
        middle = middle[np.unique(np.linspace(0, len(middle) - 1, count).round().astype(int))]
    return middle


def hand_views_from_take(take_path: str | os.PathLike, rig: CameraRig, hand: HandFrames, frames: Sequence[int],
                         masks: np.ndarray | str = "truth", scale: float = 1.0,
                         behind: dict[str, np.ndarray] | None = None) -> tuple[torch.Tensor, list[Views]]:
    """(poses (P,26), views per pose) for rows `frames` of `hand` (any camera subset of the take).

    masks: "truth" (ground_truth.h5 labels 1 and 3) or an array (P,C,H,W) bool in rig order; the
    hand needs masks, as its model holds nothing but the hand. A pose's views are the cameras
    that have its frame and see the hand unoccluded (see the module doc); Views.ids names them.
    views[i] belongs to frames[i] always: a pose no camera sees well gets an empty Views, which
    train_hand and evaluate_hand pass over. behind: the empty scene (empty_scene) for the views'
    backgrounds.
    """
    take = _open(take_path, rig)
    frames = [int(f) for f in frames]
    if not frames:
        raise ValueError("no frames asked for")
    bad = [f for f in frames if not 0 <= f < len(hand)]
    if bad:
        raise TakeInputError(f"{hand.source}: no frame {bad[0]} ({len(hand)} frames)")
    columns = []
    for cam in rig.ids:
        if cam not in hand.cameras:
            raise TakeInputError(f"{hand.source}: no camera {cam!r}")
        columns.append(hand.cameras.index(cam))
    index = hand.frame_index[np.asarray(frames)][:, columns]
    angles = np.asarray(hand.angles, np.float64)[frames]
    if not np.isfinite(angles).all():
        bad = frames[int(np.flatnonzero(~np.isfinite(angles).all(1))[0])]
        raise TakeInputError(f"{hand.source}: frame {bad} has NaN joint angles (the hand was not fitted there)")
    if isinstance(masks, str):
        if masks != "truth":
            raise ValueError(f"masks must be an array or 'truth', not {masks!r}")
        masks = np.isin(truth_labels(take_path, rig.ids, _seq_of(take, rig.ids, index)), HAND_LABELS)
    masks = np.asarray(masks, bool)
    if masks.shape[:2] != index.shape:
        raise ValueError(f"masks has shape {masks.shape[:2]} for {index.shape[0]} frames x {len(rig)} cameras")
    per_cam = [take.read_frames(cam, index[:, c]) for c, cam in enumerate(rig.ids)]
    joints = HandSkeleton(hand.bone_lengths).forward(angles)  # (P,21,3)
    uv = rig.project(joints.reshape(-1, 3)).reshape(len(rig), len(frames), 21, 2)
    views = []
    for p in range(len(frames)):
        use = [c for c in range(len(rig)) if index[p, c] >= 0 and _hand_visible(masks[p, c], uv[c, p])]
        if use:
            sub = rig.subset([rig.ids[c] for c in use])
            views.append(_views(sub, [per_cam[c][int(index[p, c])] for c in use], masks[p, use], scale, behind))
        else:  # kept, empty, so that views[i] stays the view set of frames[i]
            views.append(Views(torch.zeros(0, 1, 1, 3), torch.zeros(0, 3, 3), torch.zeros(0, 4, 4),
                               torch.zeros(0, 1, 1, dtype=torch.bool), ()))
    if not any(len(v) for v in views):
        raise TakeInputError(f"{take.path}: no camera sees the hand unoccluded in the frames asked for")
    return torch.as_tensor(angles, dtype=torch.float32), views


def _hand_visible(mask: np.ndarray, uv: np.ndarray) -> bool:
    """Whether the joints (21,2) that project into the image land on the (2-pixel dilated) mask."""
    h, w = mask.shape
    px = np.rint(uv).astype(np.int64)
    inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    if inside.sum() < 11:  # most of the hand is out of the picture
        return False
    grown = cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    return float(grown[px[inside, 1], px[inside, 0]].mean()) >= JOINTS_ON_MASK
