"""A release capture's pose files and masks into DATASET.h5 (docs/datasets.md, "Import").

Frame groups are the release's: its synced videos are index-aligned, so group g is frame g of
every camera (the take's frame index of that frame where it was kept, else -1), at the median of
the cameras' timestamps. They are saved as the take's frame_groups.npz, so every later stage
works on the same groups as the imported annotation. Keypoints in the release are in undistorted
pixels of the same K; they are distorted back through the calibration, as DATASET.h5 keeps raw
pixels. Joint angles are mapped
with brics_angles; where the mapped pose lies far from the release's own keypoints_3d (MANUS's
angles are relative to a Blender rest pose that is not released) our skeleton is fitted to the
keypoints_3d instead, and the record says which.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from dataset_tools.annotate import filter_angles
from dataset_tools.calibration.formats.checks import unit_scale
from dataset_tools.hand.bones import estimate_bone_lengths
from dataset_tools.hand.ik import fit_hand
from dataset_tools.keypoints.keypoints2d import CameraKeypoints, TakeKeypoints, write_keypoints_h5
from dataset_tools.sync import RELEASE_METHOD, TakeGroups, save_groups
from manus_core.cameras import CameraRig
from manus_core.dataset import (
    FLAGS,
    DatasetWriter,
    TakeAnnotation,
    add_arrays,
    skeleton_description,
    software_version,
    take_key,
)
from manus_core.errors import BoneLengthError, ReleaseError
from manus_core.frames_csv import FILE_NAME as FRAMES_CSV
from manus_core.frames_csv import frames_csv_digest
from manus_core.provenance import file_sha256, provenance_attrs, stage_inputs
from manus_core.skeleton import DEFAULT_BONE_LENGTHS, HandSkeleton
from manus_core.take import Take

from .brics_angles import from_release
from .brics_files import MASKS, OBJECT_MASKS, POSE_DUMPS, frame_files, read_bone_lengths, read_points, read_pose

MAPPED_MARGIN_M = 0.005   # mapped angles this much further (median) from keypoints_3d than a fit: fit instead


def release_groups(take: Take, fps: float) -> tuple[np.ndarray, TakeGroups]:
    """(frame numbers (T,), the take's groups): group g is frame g of every synced video (the take's
    frame index of that frame where it was kept, else -1), at the median of the cameras' timestamps."""
    per_cam = [take.camera_frames(cam) for cam in take.cameras]
    count = max(int(f["seq"].max()) + 1 for f in per_cam if len(f["seq"]))
    frame_index = np.full((count, len(per_cam)), -1, np.int64)
    t = np.full((count, len(per_cam)), np.nan)
    for c, f in enumerate(per_cam):
        frame_index[f["seq"], c] = np.arange(len(f["seq"]))
        t[f["seq"], c] = f["t_host_ns"]
    present = (frame_index >= 0).any(1)
    frame_ns = np.nanmedian(t[present], axis=1).round().astype(np.int64)
    groups = TakeGroups(take.cameras, frame_ns, frame_index[present], t[present], RELEASE_METHOD, {"fps": fps},
                        frames_csv_digest(take.path / FRAMES_CSV))
    return np.flatnonzero(present), groups


def pose_folder(capture: Path, annotations: Path | None) -> Path | None:
    """CAPTURE/pose_dumps, or ANNOTATIONS/.../SEQ/pose_dumps for the capture's sequence name."""
    if (capture / POSE_DUMPS).is_dir():
        return capture / POSE_DUMPS
    if annotations is None:
        return None
    seq = capture.name.split("_session_")[-1]
    found = sorted(annotations.glob(f"**/{seq}/{POSE_DUMPS}"))
    return found[0] if found else None


def _distort(rig: CameraRig, points: np.ndarray) -> np.ndarray:
    """Undistorted pixels (C,N,2) of the same K to raw pixels (C,N,2)."""
    K = rig.K
    y = (points[..., 1] - K[:, 1, 2, None]) / K[:, 1, 1, None]
    x = (points[..., 0] - K[:, 0, 2, None] - K[:, 0, 1, None] * y) / K[:, 0, 0, None]
    xd = rig.distort(np.stack([x, y], -1))
    return np.stack([K[:, 0, 0, None] * xd[..., 0] + K[:, 0, 1, None] * xd[..., 1] + K[:, 0, 2, None],
                     K[:, 1, 1, None] * xd[..., 1] + K[:, 1, 2, None]], -1)


def _frames(folder: Path, numbers: np.ndarray, width: int) -> np.ndarray | None:
    """(T,21,width) of a folder of per-frame files (NaN where none), None when it has none."""
    files = frame_files(folder)
    if not files:
        return None
    out = np.full((len(numbers), 21, width), np.nan)
    row = {int(n): i for i, n in enumerate(numbers)}
    for k, path in files.items():
        if k in row:
            out[row[k]] = read_points(path, width)
    return out


def _angles(folder: Path, numbers: np.ndarray, scale: float) -> np.ndarray | None:
    files = frame_files(folder)
    if not files:
        return None
    translation, eulers = np.full((len(numbers), 3), np.nan), np.full((len(numbers), 21, 3), np.nan)
    row = {int(n): i for i, n in enumerate(numbers)}
    for k, path in files.items():
        if k in row:
            translation[row[k]], eulers[row[k]] = read_pose(path)
    return from_release(translation * scale, eulers)


def _keypoints2d(folder: Path, rig: CameraRig, numbers: np.ndarray) -> np.ndarray | None:
    per_cam = [_frames(folder / cam, numbers, 3) for cam in rig.ids]
    if all(p is None for p in per_cam):
        return None
    out = np.full((len(numbers), len(rig), 21, 3), np.nan)
    out[..., 2] = 0.0
    for c, p in enumerate(per_cam):
        if p is not None:
            out[:, c] = p
    raw = _distort(rig, out[..., :2].transpose(1, 0, 2, 3).reshape(len(rig), -1, 2))
    out[..., :2] = raw.reshape(len(rig), len(numbers), 21, 2).transpose(1, 0, 2, 3)
    out[~(np.isfinite(out[..., :2]).all(-1) & (out[..., 2] > 0))] = [np.nan, np.nan, 0.0]
    return out


def _pose_residual(angles: np.ndarray, bones: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Per frame, the RMS distance (m) of the skeleton posed by `angles` from the joints X it saw."""
    with np.errstate(invalid="ignore"):
        d = np.linalg.norm(HandSkeleton(bones).forward(np.nan_to_num(angles)) - X, axis=-1)
        out = np.sqrt(np.nanmean(np.where(np.isfinite(d), d * d, np.nan), axis=1))
    out[~np.isfinite(angles).all(1)] = np.nan
    return out


def _annotation(take: Take, folder: Path, rig: CameraRig, numbers, frame_ns, frame_index, scale: float,
                calibration: Path | None) -> tuple[TakeAnnotation, list[str]] | None:
    kp2 = _keypoints2d(folder / "keypoints_2d", rig, numbers)
    kp3 = _frames(folder / "keypoints_3d", numbers, 4)
    raw = _angles(folder / "joint_angles", numbers, scale)
    filtered = _angles(folder / "joint_angles_filtered", numbers, scale)
    if kp2 is None and kp3 is None and raw is None:
        return None
    said = []
    T, C = frame_index.shape
    if kp3 is not None:
        X = kp3[..., :3] * scale
        X[kp3[..., 3] <= 0] = np.nan
        said.append(f"keypoints_3d ({int(np.isfinite(X).all(-1).any(-1).sum())} frames)")
    else:
        X = np.full((T, 21, 3), np.nan)
    if (folder / "bone_lens.json").is_file():
        bones, bone_source = read_bone_lengths(folder / "bone_lens.json") * scale, "release:bone_lens.json"
    else:
        try:
            bones, bone_source = estimate_bone_lengths(X).bone_lengths, "estimated from keypoints_3d"
        except BoneLengthError:
            bones, bone_source = DEFAULT_BONE_LENGTHS, "default (no bone_lens.json, too few keypoints_3d)"
    source = "release:joint_angles"
    fitted = fit_hand(X, bones)[0] if np.isfinite(X).all(-1).sum(-1).max() >= 3 else None
    if raw is not None and fitted is not None:
        mapped_m, fitted_m = (float(np.nanmedian(_pose_residual(a, bones, X))) for a in (raw, fitted))
        source += f" (pose {mapped_m * 1000:.1f} mm from keypoints_3d; a fit: {fitted_m * 1000:.1f} mm)"
        if not mapped_m <= fitted_m + MAPPED_MARGIN_M:
            raw, filtered = None, None
            source = (f"fitted to keypoints_3d ({fitted_m * 1000:.1f} mm; the release's angles posed our skeleton "
                      f"{mapped_m * 1000:.1f} mm from them)")
    if raw is None and fitted is not None:
        raw = fitted
        source = source if source.startswith("fitted") else "fitted to keypoints_3d"
    if raw is None:
        raw = np.full((T, 26), np.nan)
    if filtered is None:
        filtered = filter_angles(raw, frame_ns) if np.isfinite(raw).any() else raw.copy()
    said.append(f"joint angles ({source})")
    if kp2 is None:
        kp2 = np.full((T, C, 21, 3), np.nan)
        kp2[..., 2] = 0.0
    else:
        said.insert(0, f"keypoints_2d ({int((kp2[..., 2] > 0).any(-1).any(-1).sum())} frames)")
    residual = _pose_residual(raw, bones, X).astype(np.float32)
    flags = np.zeros(T, np.uint8)
    flags[~np.isfinite(raw).all(1)] |= FLAGS["no_hand"]
    flags[~np.isfinite(X).all((1, 2))] |= FLAGS["missing_joints"]
    flags[(frame_index < 0).any(1)] |= FLAGS["incomplete_group"]
    calib = {"calibration": str(calibration or ""),
             "calibration_sha256": file_sha256(calibration) if calibration and calibration.is_file() else ""}
    attrs = {"kind": str(take.meta.get("kind", "")), "take": str(take.path), "status": "complete",
             "skeleton": skeleton_description(HandSkeleton(bones)), "software": software_version(),
             "keypoint_source": f"release:{folder}", "bone_source": bone_source, "filter": {"source": source},
             "frame_groups": "release (synced videos are index-aligned)", "cameras_left_out": [],
             **calib, **provenance_attrs("annotate", stage_inputs(take, imported=str(folder)))}
    views = (kp2[..., 2] > 0).sum(1).astype(np.int16)
    ann = TakeAnnotation(take_key(take.path), tuple(rig.ids), frame_ns, frame_index, kp2.astype(np.float32), X,
                         np.full((T, 21), np.nan, np.float32), views, raw, filtered, bones, residual, flags, attrs)
    return ann, said


def _keypoints_file(take: Take, ann: TakeAnnotation, folder: Path) -> None:
    """TAKE/keypoints2d.h5 of the release's 2D keypoints (raw pixels), per camera frame, so that
    `annotate` (--keypoints auto or file) triangulates them like a detector's."""
    cameras = {}
    for c, cam in enumerate(ann.cameras):
        kp = np.full((take.frame_count(cam), 21, 3), np.nan, np.float32)
        kp[..., 2] = 0.0
        rows = ann.frame_index[:, c] >= 0
        kp[ann.frame_index[rows, c]] = ann.keypoints2d[rows, c]
        cameras[cam] = CameraKeypoints(kp, np.full((len(kp), 4), np.nan), np.full(len(kp), np.nan))
    write_keypoints_h5(take.path / "keypoints2d.h5", TakeKeypoints(
        cameras, "release", str(folder / "keypoints_2d"), "release", {"take": str(take.path)}))


def _masks(take: Take, capture: Path, rig: CameraRig, numbers: np.ndarray, frame_ns: np.ndarray
           ) -> dict[str, np.ndarray] | None:
    """masks/hand, masks/object and masks/frame_ns from the release's RGBA images (alpha = mask)."""
    folders = {"hand": capture / MASKS, "object": capture / OBJECT_MASKS}
    if take.meta.get("kind") == "object":
        folders = {"object": capture / MASKS}
    files = {part: {cam: frame_files(folder / cam, ".png") for cam in rig.ids} for part, folder in folders.items()}
    with_mask = sorted({k for part in files.values() for per in part.values() for k in per})
    rows = [i for i, n in enumerate(numbers) if int(n) in with_mask]
    if not rows:
        return None
    w, h = (int(v) for v in rig.size[0])
    out = {part: np.zeros((len(rows), len(rig), h, w), bool) for part in ("hand", "object")}
    for part, per_cam in files.items():
        for c, cam in enumerate(rig.ids):
            for r, row in enumerate(rows):
                path = per_cam[cam].get(int(numbers[row]))
                if path is None:
                    continue
                image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
                if image is None or image.ndim != 3 or image.shape[2] != 4:
                    raise ReleaseError(f"{path}: not an RGBA image (the release's masks are the alpha channel)")
                if image.shape[:2] != (h, w):
                    raise ReleaseError(f"{path}: {image.shape[1]}x{image.shape[0]}, camera {cam} is {w}x{h}")
                out[part][r, c] = image[..., 3] > 127
    return {"masks/hand": out["hand"], "masks/object": out["object"], "masks/frame_ns": frame_ns[rows]}


def import_poses(take_dir: Path, capture: Path, rig: CameraRig, cameras: list[str], *,
                 annotations: Path | None = None, units: str | None = None,
                 calibration: Path | None = None) -> list[str]:
    """The take's frame groups (TAKE/frame_groups.npz, the release's alignment, which the sync report
    keeps), and the capture's pose files and masks into SESSION/DATASET.h5 as take SESSION/TAKE;
    returns what was read."""
    take = Take(take_dir)
    rig = rig.subset(cameras)
    numbers, groups = release_groups(take, float(take.fps or 30.0))
    save_groups(take.path, groups)
    frame_ns, frame_index = groups.frame_ns, groups.frame_index
    dataset = take.path.parent / "DATASET.h5"
    said: list[str] = []
    folder = pose_folder(capture, annotations)
    found = None if folder is None else _annotation(take, folder, rig, numbers, frame_ns, frame_index,
                                                    unit_scale(units, str(folder)), calibration)
    if found is not None:
        with DatasetWriter(dataset, force=True) as writer:
            writer.add(found[0])
        said += found[1]
        if said[0].startswith("keypoints_2d"):
            _keypoints_file(take, found[0], folder)
    masks = _masks(take, capture, rig, numbers, frame_ns)
    if masks is not None:
        add_arrays(dataset, take_key(take.path), masks,
                   {"mask_cameras": list(rig.ids),
                    **provenance_attrs("segment", stage_inputs(take, imported=str(capture / MASKS)))},
                   stage="segment")
        said.append(f"masks ({len(masks['masks/frame_ns'])} frames)")
    return said
