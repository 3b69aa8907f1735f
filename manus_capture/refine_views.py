"""What pose refinement compares MANUS-Hand with: every (frame group, camera) view of a take's hand,
undistorted and cut to one window size, with its hand and object masks and the 2D keypoints.

The images of a take are distorted; MANUS-Hand renders through pinhole intrinsics. Each camera's
undistortion map is computed once and only the window around the hand is remapped, so the cost
follows the hand's pixels rather than the image size. The window of a view is centred on the
(undistorted) hand mask, or on the projected joints of the initial pose where the mask is empty
(the hand hidden by the object, or missed by segment: the mask term then pushes the hand out of
a region where the images see none). Pixels on the object are left out of the image terms: the
object hides what is behind it, and the hand model holds nothing but the hand.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import h5py
import numpy as np
import torch

from manus_capture.splat.takes import mask_cameras
from manus_core.cameras import CameraRig, scale_intrinsics
from manus_core.dataset import TakeAnnotation
from manus_core.errors import RefineInputError
from manus_core.progress import Progress, silent
from manus_core.skeleton import HandSkeleton
from manus_core.take import Take

TILE = 8   # windows are a multiple of the rasterizer's tile


@dataclass
class PoseViews:
    """Views of T frame groups: V windows of one size (h, w), each of one frame and one camera.

    frame (V,) rows of the take's annotation; camera (V,) indices into `cameras`; images (V,h,w,3)
    uint8 RGB; hand and valid (V,h,w) bool (valid: not on the object); Ks (V,3,3) pinhole
    intrinsics of the windows; viewmats (V,4,4) world to camera. keypoints (T,C,21,3): the
    annotation's 2D keypoints undistorted into the same pinhole pixels (before the window shift),
    confidence last (0: none); cam_Ks (C,3,3) and cam_viewmats (C,4,4) of the whole (scaled)
    images, for them.
    """

    frame: np.ndarray
    camera: np.ndarray
    images: torch.Tensor
    hand: torch.Tensor
    valid: torch.Tensor
    Ks: torch.Tensor
    viewmats: torch.Tensor
    keypoints: torch.Tensor
    cam_Ks: torch.Tensor
    cam_viewmats: torch.Tensor
    cameras: tuple[str, ...]
    has_masks: np.ndarray      # (T,) bool: the frame group has masks (segment --every may skip some)

    def __len__(self) -> int:
        return len(self.frame)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the windows."""
        return int(self.images.shape[2]), int(self.images.shape[1])

    @classmethod
    @torch.no_grad()
    def rendered(cls, model, angles: np.ndarray, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                 keypoint_noise_px: float = 0.0, outlier_rate: float = 0.0, outlier_px: float = 30.0,
                 seed: int = 0, **render) -> "PoseViews":
        """Views of a known hand (a HandGaussians) posed by angles (T,26) in C whole images: the
        renders are the images, alpha > 0.5 the masks, its joints projected the keypoints (with
        Gaussian noise and a fraction of outliers moved by outlier_px). For tests and benchmarks."""
        T, C = len(angles), len(viewmats)
        poses = torch.as_tensor(np.asarray(angles), dtype=torch.float32, device=viewmats.device)
        rgb, alpha = model.render(poses.repeat_interleave(C, 0), viewmats.repeat(T, 1, 1), Ks.repeat(T, 1, 1),
                                  width, height, **render)
        joints = model.skeleton.forward(poses)
        xc = torch.einsum("cij,fnj->fcni", viewmats[:, :3, :3], joints) + viewmats[None, :, None, :3, 3]
        uv = torch.einsum("cij,fcnj->fcni", Ks, xc)
        uv = (uv[..., :2] / uv[..., 2:]).cpu()
        g = torch.Generator().manual_seed(seed)
        uv = uv + keypoint_noise_px * torch.randn(uv.shape, generator=g)
        uv[torch.rand(uv.shape[:-1], generator=g) < outlier_rate] += outlier_px
        keypoints = torch.cat([uv, torch.ones(*uv.shape[:-1], 1)], -1)
        # in host memory, as pose_views': refinement moves a chunk at a time to the model's device
        Ks, viewmats = Ks.float().cpu(), viewmats.float().cpu()
        return cls(np.repeat(np.arange(T), C), np.tile(np.arange(C), T),
                   (rgb.clamp(0, 1) * 255).round().to(torch.uint8).cpu(), (alpha[..., 0] > 0.5).cpu(),
                   torch.ones(T * C, height, width, dtype=torch.bool), Ks.repeat(T, 1, 1), viewmats.repeat(T, 1, 1),
                   keypoints, Ks, viewmats, tuple(f"c{i}" for i in range(C)), np.ones(T, bool))


def viewmats_of(rig: CameraRig) -> torch.Tensor:
    """World-to-camera 4x4 matrices (C,4,4) float32 of a rig."""
    m = np.tile(np.eye(4), (len(rig), 1, 1))
    m[:, :3, :3], m[:, :3, 3] = rig.R, rig.t
    return torch.as_tensor(m, dtype=torch.float32)


def mask_rows(dataset: Path, key: str, frame_ns: np.ndarray, cameras: list[str]) -> tuple[np.ndarray, list[int]]:
    """The row of masks/hand and masks/object of every annotation row (T,) (-1: none; segment
    --every leaves some out) and the masks' column of every camera."""
    with h5py.File(dataset, "r") as f:
        if "masks/hand" not in f[key] or "masks/object" not in f[key]:
            raise RefineInputError(f"{dataset}: take {key} has no hand and object masks; run `manus-capture "
                                   "segment` on it first (refinement compares silhouettes)")
        mask_ns = f[key]["masks/frame_ns"][()]
    mask_cams = mask_cameras(dataset, key)   # also refuses masks of another recording than the annotation
    missing = [c for c in cameras if c not in mask_cams]
    if missing:
        raise RefineInputError(f"{dataset}: take {key} has no masks of cameras {', '.join(missing)}")
    lookup = {int(t): i for i, t in enumerate(mask_ns)}
    return np.array([lookup.get(int(t), -1) for t in frame_ns]), [mask_cams.index(c) for c in cameras]


def _window(mask: np.ndarray, joints_uv: np.ndarray, size: tuple[int, int]) -> tuple[int, int, int, int] | None:
    """The box (x0, y0, x1, y1) inclusive to centre a window on: the mask's, else the joints'."""
    ys, xs = np.nonzero(mask)
    if len(xs):
        return int(xs.min()), int(ys.min()), int(xs.max()), int(ys.max())
    w, h = size
    inside = (joints_uv[:, 0] >= 0) & (joints_uv[:, 0] < w) & (joints_uv[:, 1] >= 0) & (joints_uv[:, 1] < h)
    if inside.sum() < 11:   # most of the hand outside the picture: nothing to compare with
        return None
    lo, hi = joints_uv[inside].min(0), joints_uv[inside].max(0)
    return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])


def _undistort_keypoints(kp: np.ndarray, K: np.ndarray, dist: np.ndarray, K_out: np.ndarray) -> np.ndarray:
    """Keypoints (T,21,3) of one camera in pinhole pixels of K_out; missing ones stay [NaN, NaN, 0]."""
    out = np.full(kp.shape, np.nan, np.float32)
    out[..., 2] = 0
    ok = np.isfinite(kp[..., :2]).all(-1) & (kp[..., 2] > 0)
    if ok.any():
        pts = cv2.undistortPoints(kp[ok][:, None, :2].astype(np.float64), K, dist, P=K_out)[:, 0]
        out[ok, :2] = pts
        out[ok, 2] = kp[ok, 2]
    return out


def pose_views(take_path: Path, dataset: Path, ann: TakeAnnotation, rig: CameraRig, angles: np.ndarray,
               margin: int = 6, scale: float = 1.0, progress: Progress = silent) -> PoseViews:
    """The views of every frame group of `ann` with a fitted hand (finite `angles`) whose masks
    exist, on the cameras of both the annotation and `rig` (rig order).

    One window size for the whole take: the largest mask box plus `margin` pixels, a multiple of 8.
    Reports progress("refine views", cameras done, cameras).
    """
    take = Take(take_path)
    cameras = [c for c in rig.ids if c in ann.cameras]
    if not cameras:
        raise RefineInputError(f"{dataset}: take {ann.key} shares no camera with the calibration")
    rig = rig.subset(cameras)
    cols = [ann.cameras.index(c) for c in cameras]
    fitted = np.isfinite(angles).all(1)
    index = ann.frame_index[:, cols]
    joints = HandSkeleton(ann.bone_lengths).forward(np.where(fitted[:, None], angles, 0.0))
    T, C = index.shape
    W, H = int(rig.size[0, 0]), int(rig.size[0, 1])
    if (rig.size != rig.size[0]).any():
        raise RefineInputError(f"the cameras of {take_path} differ in image size; refine cameras of one size together")
    sw, sh = max(int(round(W * scale)), 1), max(int(round(H * scale)), 1)
    K_out = np.stack([scale_intrinsics(k, sw / W, sh / H) for k in rig.K])
    uv = np.stack([cv2.projectPoints(joints.reshape(-1, 3), cv2.Rodrigues(rig.R[c])[0], rig.t[c], K_out[c],
                                     None)[0].reshape(T, 21, 2) for c in range(C)], 1)   # (T,C,21,2)

    maps = [cv2.initUndistortRectifyMap(rig.K[c], rig.dist[c], None, K_out[c], (sw, sh), cv2.CV_32FC1)
            for c in range(C)]
    rows, columns = mask_rows(dataset, ann.key, ann.frame_ns, cameras)
    use = fitted & (rows >= 0)

    def undistorted_masks():
        """(t, c, hand, object) of every view, undistorted at the scaled size; read twice (boxes,
        then windows) rather than held: a long take's whole masks need not fit in memory."""
        with h5py.File(dataset, "r") as f:
            hand_ds, obj_ds = f[ann.key]["masks/hand"], f[ann.key]["masks/object"]
            for t in np.flatnonzero(use):
                h_row, o_row = hand_ds[int(rows[t])], obj_ds[int(rows[t])]
                for c in np.flatnonzero(index[t] >= 0):
                    mx, my = maps[c]
                    yield (t, c, cv2.remap(h_row[columns[c]].astype(np.uint8), mx, my, cv2.INTER_NEAREST) > 0,
                           cv2.remap(o_row[columns[c]].astype(np.uint8), mx, my, cv2.INTER_NEAREST) > 0)

    boxes = {}
    for t, c, hm, _ in undistorted_masks():
        box = _window(hm, uv[t, c], (sw, sh))
        if box is not None:
            boxes[t, c] = box
    if not boxes:
        raise RefineInputError(f"{take_path}: no frame group shows the hand in any camera with masks")
    spans = np.array([[b[2] - b[0] + 1, b[3] - b[1] + 1] for b in boxes.values()])
    cw = min(-(-(int(spans[:, 0].max()) + 2 * margin) // TILE) * TILE, sw)
    ch = min(-(-(int(spans[:, 1].max()) + 2 * margin) // TILE) * TILE, sh)

    views = sorted(boxes)   # by frame, then camera
    V = len(views)
    images = np.zeros((V, ch, cw, 3), np.uint8)
    Ks = np.zeros((V, 3, 3), np.float32)
    origin = np.zeros((V, 2), np.int64)
    for v, (t, c) in enumerate(views):
        x0, y0, x1, y1 = boxes[t, c]
        origin[v] = (np.clip((x0 + x1 + 1) // 2 - cw // 2, 0, sw - cw),
                     np.clip((y0 + y1 + 1) // 2 - ch // 2, 0, sh - ch))
        Ks[v] = K_out[c]
        Ks[v, :2, 2] -= origin[v]
    by_camera: dict[int, list[int]] = {}
    for v, (_, c) in enumerate(views):
        by_camera.setdefault(c, []).append(v)
    progress("refine views", 0, C)
    for done, (c, vs) in enumerate(sorted(by_camera.items()), 1):
        frames = take.read_frames(cameras[c], np.array([index[views[v][0], c] for v in vs]))
        mx, my = maps[c]
        for v in vs:
            x, y = origin[v]
            image = frames[int(index[views[v][0], c])]
            if image.shape[:2] != (H, W):
                raise RefineInputError(f"{take_path}: camera {cameras[c]} frames are {image.shape[1]}x"
                                       f"{image.shape[0]}, the calibration says {W}x{H}")
            # the window's own part of the undistortion map: only its pixels are resampled
            window = cv2.remap(image, mx[y:y + ch, x:x + cw], my[y:y + ch, x:x + cw], cv2.INTER_LINEAR)
            images[v] = window[..., ::-1]
        progress("refine views", done, C)
    hand = np.zeros((V, ch, cw), bool)
    valid = np.ones((V, ch, cw), bool)
    slot = {view: v for v, view in enumerate(views)}
    for t, c, hm, om in undistorted_masks():
        v = slot.get((t, c))
        if v is not None:
            x, y = origin[v]
            hand[v], valid[v] = hm[y:y + ch, x:x + cw], ~om[y:y + ch, x:x + cw]
    t_of, c_of = np.array([v[0] for v in views]), np.array([v[1] for v in views])
    keypoints = np.stack([_undistort_keypoints(ann.keypoints2d[:, col], rig.K[c], rig.dist[c], K_out[c])
                          for c, col in enumerate(cols)], 1)
    cam_viewmats = viewmats_of(rig)
    return PoseViews(t_of, c_of, torch.from_numpy(images), torch.from_numpy(hand), torch.from_numpy(valid),
                     torch.from_numpy(Ks), cam_viewmats[c_of],
                     torch.from_numpy(keypoints), torch.as_tensor(K_out, dtype=torch.float32), cam_viewmats,
                     tuple(cameras), use)
