"""A simulated 2D hand keypoint detector: the true joints projected, with realistic faults.

    det = SimulatedDetector(noise_px=2.0, outlier_rate=0.1, seed=0)
    keypoints2d = det.detect(rig, joints3d)            # (T,21,3) or per camera (T,C,21,3) -> (T,C,21,3)

It stands in for the ONNX detector on simulated takes, so that every stage after detection can be
scored against the ground truth. What it does to each (frame, camera, joint):

1. Projection of the true joint through the camera's full model (distortion included).
2. Visibility: a joint behind the camera, outside the image, hidden by the hand itself (capsules
   around the finger bones, triangles across the palm: `self_occlusion`), by the object (the
   rendered per-pixel labels of ground_truth.h5 where they exist for that frame, or any
   `occluder` ray test given), or dropped at random (`dropout_rate`) is missing:
   [NaN, NaN, 0].
3. Gaussian noise of `noise_px` per axis on every visible joint.
4. Outliers: a fraction `outlier_rate` of the visible joints is moved by `outlier_px` (uniform
   range) in a random direction, like a detector that picked the wrong finger. The detector does
   not know: outliers get the same confidence as the rest.
5. Confidence: uniform in `confidence` (lo, hi).

Everything is seeded and vectorized over frames, cameras and joints (the occlusion tests run in
blocks of frames to bound memory). `keypoints_for_take` builds the keypoints of a recorded
simulated take from its ground_truth.h5 (manus_core.ground_truth.GroundTruth): the joints are
interpolated to each camera's true mid-exposure time, so unsynchronized cameras see the hand
where it really was.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from manus_core.cameras import CameraRig
from manus_core.errors import SimulatedDetectorError
from manus_core.ground_truth import LABEL_BACKGROUND, LABEL_OBJECT, LABEL_WALLS, GroundTruth
from manus_core.skeleton import BONES
from manus_core.take import Take

# Radius (m) of the flesh around each bone for self-occlusion: the thumb's metacarpal (thenar) and
# the phalanges; the other metacarpals are inside the palm triangles.
DEFAULT_BONE_RADII = np.array([
    0.012, 0.0105, 0.0095, 0.0085,
    0.0, 0.009, 0.008, 0.007,
    0.0, 0.009, 0.008, 0.007,
    0.0, 0.0085, 0.0075, 0.0068,
    0.0, 0.008, 0.007, 0.0062,
])
PALM_TRIANGLES = np.array([[0, 1, 5], [0, 5, 9], [0, 9, 13], [0, 13, 17]])
OCCLUDING_LABELS = (LABEL_OBJECT, LABEL_WALLS)  # the ground truth's label classes that hide a joint
_BLOCK = 16  # frames per block of the occlusion tests

# ray-test callable: (frame (N,), origin (N,3), unit direction (N,3)) -> distance to the first hit (N,)
Occluder = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


def _segment_distances(p0: np.ndarray, p1: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """Distance between segments [p0,p1] and [q0,q1], broadcast over leading axes.

    Closest points by minimising over both parameters with clamping: the parameter on one segment
    is solved, clamped, the other recomputed from it and clamped, then the first once more.
    """
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a = (d1 * d1).sum(-1)
    e = (d2 * d2).sum(-1)
    b = (d1 * d2).sum(-1)
    c = (d1 * r).sum(-1)
    f = (d2 * r).sum(-1)
    denom = a * e - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > 1e-18, np.clip((b * f - c * e) / denom, 0.0, 1.0), 0.0)
        t = np.where(e > 1e-18, (b * s + f) / e, 0.0)
        t = np.clip(t, 0.0, 1.0)
        s = np.where(a > 1e-18, np.clip((b * t - c) / a, 0.0, 1.0), 0.0)
    diff = p0 + s[..., None] * d1 - (q0 + t[..., None] * d2)
    return np.sqrt((diff * diff).sum(-1))


def _ray_triangle(o: np.ndarray, d: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Ray parameter of the hit of o + s d with triangles abc (inf for a miss), broadcast."""
    e1, e2 = b - a, c - a
    p = np.cross(d, e2)
    det = (e1 * p).sum(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        tv = o - a
        u = (tv * p).sum(-1) * inv
        q = np.cross(tv, e1)
        v = (d * q).sum(-1) * inv
        s = (e2 * q).sum(-1) * inv
    hit = (np.abs(det) > 1e-15) & (u >= 0) & (v >= 0) & (u + v <= 1) & (s > 0)
    return np.where(hit, s, np.inf)


@dataclass
class SimulatedDetector:
    """Projects true joints into every camera and adds noise, outliers and occlusion dropouts."""

    noise_px: float = 2.0
    outlier_rate: float = 0.1
    outlier_px: tuple[float, float] = (20.0, 200.0)
    dropout_rate: float = 0.0
    confidence: tuple[float, float] = (0.8, 1.0)
    self_occlusion: bool = True
    bone_radii: np.ndarray | None = None
    margin_m: float = 0.004
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("noise_px", "outlier_rate", "dropout_rate", "margin_m"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise SimulatedDetectorError(f"SimulatedDetector: {name} = {value!r} must be finite and >= 0")
        if self.outlier_rate > 1 or self.dropout_rate > 1:
            raise SimulatedDetectorError("SimulatedDetector: outlier_rate and dropout_rate are fractions in [0, 1]")
        lo, hi = self.confidence
        if not 0 < lo <= hi <= 1:
            raise SimulatedDetectorError(f"SimulatedDetector: confidence range {self.confidence} must lie in (0, 1]")
        self.bone_radii = np.array(DEFAULT_BONE_RADII if self.bone_radii is None else self.bone_radii, float)
        if self.bone_radii.shape != (20,):
            raise SimulatedDetectorError(f"SimulatedDetector: bone_radii must be 20 radii, got {self.bone_radii.shape}")

    def detect(self, rig: CameraRig, joints3d: np.ndarray, labels: Mapping[int, np.ndarray] | None = None,
               occluder: Occluder | None = None) -> np.ndarray:
        """Keypoints (T,C,21,3) [x, y, confidence] of the joints (T,21,3), or of per-camera joints
        (T,C,21,3) (each camera's view of the hand at its own exposure time).

        labels: {frame: (C,H,W) uint8} ground-truth label images of some frames; a joint on an
        object or wall/table pixel there is occluded. occluder: a ray test for everything else.
        """
        X = np.asarray(joints3d, dtype=np.float64)
        n_c = len(rig)
        if X.ndim == 3 and X.shape[1:] == (21, 3):
            X = np.broadcast_to(X[:, None], (X.shape[0], n_c, 21, 3))
        if X.ndim != 4 or X.shape[1:] != (n_c, 21, 3):
            raise SimulatedDetectorError(f"SimulatedDetector: joints3d must be (T,21,3) or (T,{n_c},21,3), "
                                         f"got shape {np.shape(joints3d)}")
        n_t = X.shape[0]
        rng = np.random.default_rng(self.seed)
        uv, depth = _project(rig, X)
        w, h = rig.size[:, 0][None, :, None], rig.size[:, 1][None, :, None]
        visible = (depth > 0) & np.isfinite(X).all(-1) & (uv[..., 0] >= -0.5) & (uv[..., 1] >= -0.5) \
            & (uv[..., 0] <= w - 0.5) & (uv[..., 1] <= h - 0.5)
        if self.self_occlusion or occluder is not None:
            for start in range(0, n_t, _BLOCK):
                sl = slice(start, start + _BLOCK)
                visible[sl] &= ~self._occluded(rig, X[sl], np.arange(n_t)[sl], occluder)
        if labels:
            for frame, image in labels.items():
                if 0 <= frame < n_t:
                    visible[frame] &= ~_on_labels(image, uv[frame], OCCLUDING_LABELS)
        visible &= rng.random(visible.shape) >= self.dropout_rate
        noisy = uv + rng.normal(scale=self.noise_px, size=uv.shape) if self.noise_px > 0 else uv.copy()
        outlier = visible & (rng.random(visible.shape) < self.outlier_rate)
        angle = rng.uniform(0, 2 * np.pi, visible.shape)
        dist = rng.uniform(*self.outlier_px, visible.shape)
        shift = np.stack([np.cos(angle), np.sin(angle)], -1) * dist[..., None]
        noisy = np.where(outlier[..., None], noisy + shift, noisy)
        conf = rng.uniform(*self.confidence, visible.shape)
        out = np.concatenate([noisy, conf[..., None]], -1)
        out[~visible] = (np.nan, np.nan, 0.0)
        return out

    def _occluded(self, rig: CameraRig, X: np.ndarray, frames: np.ndarray, occluder: Occluder | None) -> np.ndarray:
        """(t,C,21) bool: the ray from the camera to the joint is blocked before the joint."""
        centers = rig.centers[None, :, None, :]                       # (1,C,1,3)
        ray = X - centers
        length = np.linalg.norm(ray, axis=-1)
        unit = ray / length[..., None]
        # The ray stops short of the joint by the flesh around it, so a joint never hides itself.
        hidden = np.zeros(X.shape[:3], bool)
        if self.self_occlusion:
            # Each camera's own view of the hand (its exposure time) occludes its joints.
            keep = np.flatnonzero(self.bone_radii > 0)
            a, b = X[:, :, None, BONES[keep, 0]], X[:, :, None, BONES[keep, 1]]   # (t,C,1,B,3)
            radii = self.bone_radii[keep]
            stop = np.maximum(length[..., None] - radii - self.margin_m, 0.0)   # (t,C,21,B)
            end = centers[..., None, :] + unit[..., None, :] * stop[..., None]
            d = _segment_distances(np.broadcast_to(centers[..., None, :], end.shape), end, a, b)
            hidden |= (d < radii).any(-1)
            tri = X[:, :, None, PALM_TRIANGLES]                        # (t,C,1,4,3,3)
            s = _ray_triangle(centers[..., None, :], unit[..., None, :], tri[..., 0, :], tri[..., 1, :],
                              tri[..., 2, :])
            hidden |= (s < length[..., None] - self.margin_m - 0.005).any(-1)
        if occluder is not None:
            n_c = X.shape[1]
            f = np.broadcast_to(frames[:, None, None], X.shape[:3]).reshape(-1)
            o = np.broadcast_to(centers, X.shape).reshape(-1, 3)
            hit = np.asarray(occluder(f, o, unit.reshape(-1, 3)), dtype=np.float64).reshape(len(X), n_c, 21)
            hidden |= hit < length - self.margin_m
        return hidden


def _project(rig: CameraRig, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-camera points (T,C,J,3) to distorted pixels (T,C,J,2) and depths (T,C,J)."""
    Xc = np.einsum("cij,tcnj->tcni", rig.R, X) + rig.t[None, :, None, :]
    z = Xc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = np.where((z > 0)[..., None], Xc[..., :2] / z[..., None], np.nan)
    n_t, n_c, n_j = z.shape
    xd = rig.distort(xy.transpose(1, 0, 2, 3).reshape(n_c, n_t * n_j, 2)).reshape(n_c, n_t, n_j, 2)
    xd = xd.transpose(1, 0, 2, 3)
    K = rig.K[None, :, None]
    u = K[..., 0, 0] * xd[..., 0] + K[..., 0, 1] * xd[..., 1] + K[..., 0, 2]
    v = K[..., 1, 1] * xd[..., 1] + K[..., 1, 2]
    return np.stack([u, v], -1), z


def _on_labels(image: np.ndarray, uv: np.ndarray, classes: tuple[int, ...]) -> np.ndarray:
    """(C,21) bool: the pixel under each projected joint has one of the label classes."""
    image = np.asarray(image)
    n_c = uv.shape[0]
    px = np.rint(np.nan_to_num(uv, nan=-1.0)).astype(np.int64)
    inside = (px[..., 0] >= 0) & (px[..., 1] >= 0) & (px[..., 0] < image.shape[2]) & (px[..., 1] < image.shape[1])
    cams = np.broadcast_to(np.arange(n_c)[:, None], inside.shape)
    values = image[cams, np.clip(px[..., 1], 0, image.shape[1] - 1), np.clip(px[..., 0], 0, image.shape[2] - 1)]
    return inside & np.isin(values, classes)


# --- simulated takes -------------------------------------------------------------------------------

def true_rig(gt: GroundTruth, cam_ids: tuple[str, ...] | None = None) -> CameraRig:
    """The exact cameras of a simulated take (from its ground truth), in the order of cam_ids."""
    rig = gt.cameras.rig()
    missing = [c for c in cam_ids or () if c not in rig.ids]
    if missing:
        raise SimulatedDetectorError(f"{gt.path}: no camera {', '.join(missing)}")
    return rig.subset(cam_ids) if cam_ids is not None else rig


def exposure_times(gt: GroundTruth, cam_ids: tuple[str, ...], host_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """True mid-exposure (ns, float; NaN where no frame) of the frames that reached the host at
    host_ns (T,C) (NaN or -1: no frame), the camera's last exposure before the arrival, and that
    exposure's tick (the ground truth's frame axis; -1 where no frame)."""
    ids = list(gt.cameras.ids)
    missing = [c for c in cam_ids if c not in ids]
    if missing:
        raise SimulatedDetectorError(f"{gt.path}: no camera {', '.join(missing)}")
    frames = gt.frames
    host = np.asarray(host_ns, dtype=np.float64)
    out = np.full(host.shape, np.nan)
    ticks = np.full(host.shape, -1, np.int64)
    for c, cam in enumerate(cam_ids):
        row = ids.index(cam)
        exp = frames.exposure_mid_ns[row]
        cols = np.flatnonzero((exp >= 0) & ~frames.dropped[row])
        order = np.argsort(exp[cols], kind="stable")
        seen, cols = exp[cols][order].astype(np.float64), cols[order]
        ok = np.flatnonzero(np.isfinite(host[:, c]) & (host[:, c] >= 0))
        k = np.searchsorted(seen, host[ok, c], side="right") - 1
        out[ok[k >= 0], c] = seen[k[k >= 0]]
        ticks[ok[k >= 0], c] = cols[k[k >= 0]]
    return out, ticks


def joints_at(tick_ns: np.ndarray, joints3d: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
    """Joints (F,21,3) given on the ticks tick_ns (F,), at times t_ns (any shape, ns): linear between
    the ticks (the motion is smooth; the error is far below a micrometre at 120 fps). NaN stays NaN."""
    ticks = np.asarray(tick_ns, np.float64)
    joints = np.asarray(joints3d).reshape(len(ticks), -1)
    t = np.asarray(t_ns, dtype=np.float64)
    flat = t.reshape(-1)
    pos = np.interp(np.nan_to_num(flat, nan=ticks[0]), ticks, np.arange(len(ticks)))
    i0 = np.clip(np.floor(pos).astype(np.int64), 0, len(ticks) - 1)
    i1 = np.minimum(i0 + 1, len(ticks) - 1)
    frac = (pos - i0)[:, None]
    out = joints[i0] * (1 - frac) + joints[i1] * frac
    out[~np.isfinite(flat)] = np.nan
    return out.reshape(t.shape + (21, 3))


class _GroundTruthLabels(Mapping):
    """{row of the take's frame groups: (C,H,W) labels} from ground_truth.h5, read one row at a
    time; a camera whose frame in that row has no labels gets background everywhere."""

    def __init__(self, gt: GroundTruth, size: tuple[int, int], rows: dict[int, list[tuple[int, int, int]]],
                 n_cameras: int) -> None:
        self.gt, self.size, self.rows = gt, size, rows   # row -> [(camera, gt camera, label index)]
        self.n_cameras = n_cameras

    def __getitem__(self, row: int) -> np.ndarray:
        cams, gt_cams, index = (list(v) for v in zip(*self.rows[row]))
        out = np.full((self.n_cameras,) + self.size, LABEL_BACKGROUND, np.uint8)
        images = self.gt.label_images(gt_cams, index)[:, :self.size[0], :self.size[1]]
        for c, image in zip(cams, images):
            out[c, :image.shape[0], :image.shape[1]] = image
        return out

    def __iter__(self):
        return iter(self.rows)

    def __len__(self) -> int:
        return len(self.rows)


def keypoints_for_take(gt: GroundTruth, rig: CameraRig, host_ns: np.ndarray,
                       detector: SimulatedDetector | None = None, use_labels: bool = True) -> np.ndarray:
    """Keypoints (T,C,21,3) of a simulated take's frame groups.

    gt: the take's ground truth (with a hand); rig: the cameras (in the order of the columns of
    host_ns); host_ns (T,C): host arrival of each camera's frame in each group (NaN or -1: none).
    Frames whose tick has ground-truth labels take the object's occlusion from them.
    """
    detector = detector or SimulatedDetector()
    exposure, ticks = exposure_times(gt, rig.ids, host_ns)
    joints = joints_at(gt.frames.tick_ns, gt.hand.joints3d, exposure)
    labels = None
    if use_labels and len(gt.label_frames):
        label_index = {int(f): i for i, f in enumerate(gt.label_frames)}
        ids = list(gt.cameras.ids)
        rows: dict[int, list[tuple[int, int, int]]] = {}
        for r, c in zip(*np.nonzero(np.isin(ticks, list(label_index)))):
            rows.setdefault(int(r), []).append((int(c), ids.index(rig.ids[c]), label_index[int(ticks[r, c])]))
        height, width = int(rig.size[:, 1].max()), int(rig.size[:, 0].max())
        labels = _GroundTruthLabels(gt, (height, width), rows, len(rig.ids))
    kp = detector.detect(rig, joints, labels=labels)
    kp[~np.isfinite(exposure)] = (np.nan, np.nan, 0.0)
    return kp


def simulated_take_keypoints(take: Take, frame_index: np.ndarray, detector: SimulatedDetector) -> np.ndarray:
    """Keypoints (T,C,21,3) of a recorded simulated take's frame groups (frame_index (T,C), -1: none).

    The `--keypoints simulated` ablation: it reads the take's ground truth, so annotate uses it only
    when asked for by name, never by default.
    """
    gt = GroundTruth.of_take(take.path)  # names the file when the take has no ground truth
    host = np.full(frame_index.shape, np.nan)
    for c, cam in enumerate(take.cameras):
        ok = frame_index[:, c] >= 0
        host[ok, c] = take.camera_frames(cam)["t_host_ns"][frame_index[ok, c]]
    return keypoints_for_take(gt, true_rig(gt, take.cameras), host, detector)
