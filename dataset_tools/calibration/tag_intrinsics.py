"""Each camera's intrinsics from the wall tags it sees, as MANUS calibrated its cube: no board.

The tag corners are known points on several walls: a non-planar target, which one view of a
static camera calibrates (as a calibration cube does). Per camera: linear and generic starts
(DLT on the corners, its projection matrix split into K and pose; the image centre with a few
focal lengths), OpenCV's calibrateCamera on that one view, and the distortion model the corners
constrain, chosen by the Bayesian information criterion: radial terms need corners away from
the centre, tangential ones corners near the image's corners. The joint adjustment (tag_rig)
refines these with every pose; `uncertainty` gives each camera's standard deviations from that
adjustment's Jacobian, and `Uncertainty.weak` says what a camera's corners do not pin down.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.linalg import rq

from manus_core.rotations import rotvec_to_matrix

from .bundle import N_INTRINSICS, BundleState, Observations, residuals_of
from .detect import Detection

MIN_POINTS = 24          # six tags: 11 unknowns of the DLT, with a margin against mis-decodes
NON_PLANAR = 0.05        # the corners' third spread over their first: two walls or more
MIN_SIDE_PX = 12.0       # tags seen smaller than this do not take part (see corner_table)
# nor tags seen at a slant beyond ~66 deg (detect's face_on): on the simulated cube their corners
# were off by 0.3-0.9 px (median), against 0.01-0.04 px for the tags seen more squarely
MIN_FACE_ON = 0.4
OUTLIER_PX = 2.0         # a corner this far off its camera's first fit (and 5x the median) is dropped
# what a well calibrated camera's adjustment leaves (1 sigma); above it a camera is named
WEAK_FX = 0.001          # relative
WEAK_CENTRE_PX = 0.0015  # of the image width
WEAK_POSITION_M = 0.0005  # a quarter of the 2 mm a camera's position should be known to

MODELS = {"k1": (4,), "k1 k2": (4, 5), "k1 k2 p1 p2": (4, 5, 6, 7)}   # columns of the adjuster's (9,) row


@dataclass(frozen=True)
class TagIntrinsics:
    """A camera's intrinsics from its tags, and what the corners constrained."""

    K: np.ndarray
    dist: np.ndarray
    model: str              # the distortion terms estimated (a key of MODELS)
    points: int             # distinct tag corners used
    reach: float            # farthest corner from the centre, over the half-diagonal
    rms_px: float

    def free(self) -> np.ndarray:
        """The adjuster's intrinsics mask (9,): fx, fy, cx, cy and the model's terms."""
        mask = np.zeros(N_INTRINSICS, bool)
        mask[:4] = True
        mask[list(MODELS[self.model])] = True
        return mask


def without_poor_tags(dets: dict[int, Detection]) -> dict[int, Detection]:
    """A camera's detections without the corners of tags seen smaller than MIN_SIDE_PX or at a
    slant (face_on below MIN_FACE_ON)."""
    return {frame: without_tags(d, [int(t) for t, q in d.info.get("tags", {}).items()
                                    if q.get("side_px", np.inf) < MIN_SIDE_PX or q.get("face_on", 1.0) < MIN_FACE_ON])
            for frame, d in dets.items()}


def without_tags(d: Detection, tags) -> Detection:
    """A detection without the corners of these tag ids."""
    keep = ~np.isin(d.ids // 4, list(tags))
    return Detection(d.ids[keep], d.xy[keep], d.info)


def corner_table(dets: dict[int, Detection], lookup: dict[int, int], world: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(world points (N,3), pixels (N,2)) of the layout's corners a static camera saw, each corner
    once: the median over the frames it was found in. Corners of tags seen smaller than
    MIN_SIDE_PX or at a slant are left out: their corners are the least precise, and on the
    cube's floor and ceiling cameras they pulled the estimate into a wrong minimum."""
    ids, xy = corner_pixels(without_poor_tags(dets))
    known = np.isin(ids, np.fromiter(lookup, int, len(lookup)))
    return world[[lookup[int(i)] for i in ids[known]]].reshape(-1, 3), xy[known]


def corner_pixels(dets: dict[int, Detection]) -> tuple[np.ndarray, np.ndarray]:
    """(corner ids, (N,2) pixels) of a static camera: each corner's median over its frames."""
    ids = np.concatenate([d.ids for d in dets.values()]) if dets else np.zeros(0, np.int64)
    xy = np.concatenate([d.xy for d in dets.values()]) if dets else np.zeros((0, 2))
    uniq, x = _median_by(ids, xy[:, 0])
    _, y = _median_by(ids, xy[:, 1])
    return uniq, np.stack([x, y], axis=1)


def _median_by(keys: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distinct keys, the median of the values of each)."""
    order = np.lexsort((values, keys))
    k, v = keys[order], values[order]
    starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]]) if len(k) else np.zeros(0, int)
    counts = np.diff(np.r_[starts, len(k)])
    return k[starts], (v[starts + (counts - 1) // 2] + v[starts + counts // 2]) / 2


def dlt(obj: np.ndarray, img: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(K, R, t) of the projection matrix that maps obj (N,3, non-planar) to img (N,2), linear
    (no distortion), with both point sets normalized first (Hartley)."""
    mo, so = obj.mean(0), np.sqrt(3) / np.mean(np.linalg.norm(obj - obj.mean(0), axis=1))
    mi, si = img.mean(0), np.sqrt(2) / np.mean(np.linalg.norm(img - img.mean(0), axis=1))
    X = np.hstack([(obj - mo) * so, np.ones((len(obj), 1))])
    u = (img - mi) * si
    A = np.zeros((2 * len(obj), 12))
    A[0::2, 0:4], A[0::2, 8:12] = X, -u[:, :1] * X
    A[1::2, 4:8], A[1::2, 8:12] = X, -u[:, 1:] * X
    P = np.linalg.svd(A)[2][-1].reshape(3, 4)
    Ti = np.array([[si, 0, -si * mi[0]], [0, si, -si * mi[1]], [0, 0, 1]])
    To = np.diag([so, so, so, 1.0])
    To[:3, 3] = -so * mo
    P = np.linalg.inv(Ti) @ P @ To
    K, R = rq(P[:, :3])
    signs = np.diag(np.sign(np.diag(K)))
    K, R = K @ signs, signs @ R
    t = np.linalg.solve(K, P[:, 3])
    if np.linalg.det(R) < 0:
        R, t = -R, -t
    K = K / K[2, 2]
    if not (np.isfinite(K).all() and K[0, 0] > 0 and K[1, 1] > 0):
        return None
    return K, R, t


def _reach(img: np.ndarray, K: np.ndarray, size: tuple[int, int]) -> float:
    w, h = size
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], float)
    half_diagonal = np.linalg.norm(corners - K[:2, 2], axis=1).max()
    return float(np.linalg.norm(img - K[:2, 2], axis=1).max() / half_diagonal)


def _fit(obj: np.ndarray, img: np.ndarray, size: tuple[int, int], K0: np.ndarray, model: str
         ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray] | None:
    """(RMS, K, dist, per-point error) of calibrateCamera on one view from K0; None if it fails."""
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3 | cv2.CALIB_FIX_K4 | cv2.CALIB_FIX_K5 | cv2.CALIB_FIX_K6
    if "k2" not in model:
        flags |= cv2.CALIB_FIX_K2
    if "p1" not in model:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    try:
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera([obj.astype(np.float32)], [img.astype(np.float32)], size,
                                                         K0.copy(), np.zeros(5), flags=flags, criteria=criteria)
    except cv2.error:
        return None
    if not (np.isfinite(K).all() and 0 < K[0, 2] < size[0] and 0 < K[1, 2] < size[1] and K[0, 0] > 0):
        return None
    proj = cv2.projectPoints(obj, rvecs[0], tvecs[0], K, dist)[0].reshape(-1, 2)
    return float(rms), K, np.ravel(dist)[:5].astype(np.float64), np.linalg.norm(proj - img, axis=1)


def _starts(obj: np.ndarray, img: np.ndarray, size: tuple[int, int]) -> list[np.ndarray]:
    """Initial K: the DLT's when plausible, and the image centre with focal lengths of 40 to 120
    degree lenses (strong barrel distortion bends the corners enough to mislead the linear start)."""
    w, h = size
    out = []
    found = dlt(obj, img)
    if found is not None and 0 < found[0][0, 2] < w and 0 < found[0][1, 2] < h:
        K = found[0].copy()
        K[0, 1] = 0.0
        out.append(K)
    for hfov in (40, 60, 80, 100, 120):
        f = (w / 2) / np.tan(np.radians(hfov) / 2)
        out.append(np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]]))
    return out


def estimate_intrinsics(obj: np.ndarray, img: np.ndarray, size: tuple[int, int]) -> TagIntrinsics | str:
    """A camera's intrinsics from known non-planar points it sees; why not, as a phrase, when the
    points cannot give them (too few, all on one wall, no start that converges).

    Every start is fitted with the fullest model and the best kept; corners far off that fit (a
    mis-decoded or moved tag) are dropped once. Then each model is fitted from it and the one
    with the lowest Bayesian information criterion wins: a term is estimated only where the
    corners constrain it."""
    if len(obj) < MIN_POINTS:
        return f"sees {len(obj)} tag corners, {MIN_POINTS} are needed to estimate its intrinsics"
    spread = np.linalg.svd(obj - obj.mean(0), compute_uv=False)
    if spread[2] < NON_PLANAR * spread[0]:
        return "sees tags on one wall only: a plane cannot give its intrinsics from one view"
    fits = [f for f in (_fit(obj, img, size, K0, "k1 k2 p1 p2") for K0 in _starts(obj, img, size)) if f is not None]
    if not fits:
        return "its intrinsics did not converge from the tag corners"
    best = min(fits, key=lambda f: f[0])
    keep = best[3] <= max(OUTLIER_PX, 5 * float(np.median(best[3])))
    if keep.sum() < MIN_POINTS:
        return f"only {int(keep.sum())} of its {len(obj)} tag corners fit one camera"
    obj, img = obj[keep], img[keep]
    scored = []
    for model in MODELS:
        fit = _fit(obj, img, size, best[1], model)
        if fit is not None:
            n, k = 2 * len(obj), 6 + 4 + len(MODELS[model])
            scored.append((n * np.log(max(fit[0], 1e-9) ** 2) + k * np.log(n), model, fit))
    if not scored:
        return "its intrinsics did not converge from the tag corners"
    _, model, (rms, K, dist, _) = min(scored, key=lambda s: s[0])
    return TagIntrinsics(K, dist, model, len(obj), _reach(img, K, size), rms)


@dataclass(frozen=True)
class Uncertainty:
    """One camera's standard deviations (1 sigma) from the adjustment it was calibrated in."""

    fx: float
    fy: float
    cx: float
    cy: float
    k1: float
    centre_m: float          # of the camera's position, the largest axis

    def weak(self, K: np.ndarray, width: int) -> list[str]:
        """What the data leaves loose, in words ([] when nothing)."""
        out = []
        if self.fx > WEAK_FX * K[0, 0]:
            out.append(f"focal length +-{self.fx / K[0, 0] * 100:.2f} %")
        if max(self.cx, self.cy) > WEAK_CENTRE_PX * width:
            out.append(f"principal point +-{max(self.cx, self.cy):.1f} px")
        if self.centre_m > WEAK_POSITION_M:
            out.append(f"position +-{self.centre_m * 1000:.1f} mm")
        return out


def uncertainty(state: BundleState, obs: Observations, cam: int, free: np.ndarray) -> Uncertainty:
    """Standard deviations of camera `cam`'s free intrinsics and of its centre: sigma^2 (J^T J)^-1
    over its own observations, with the world (the tags) held fixed as the adjustment holds it;
    sigma from its residuals. Jacobian by central differences, vectorized over the parameters."""
    sel = obs.select(obs.cam == cam)
    base = np.concatenate([state.intr[cam][free], state.cam_rvec[cam], state.cam_t[cam]])
    n_free = int(free.sum())
    steps = np.maximum(np.abs(base) * 1e-6, 1e-7)

    def residual(params: np.ndarray) -> np.ndarray:
        intr = state.intr.copy()
        intr[cam, free] = params[:n_free]
        rvec, t = state.cam_rvec.copy(), state.cam_t.copy()
        rvec[cam], t[cam] = params[n_free:n_free + 3], params[n_free + 3:]
        return residuals_of(BundleState(intr, rvec, t, state.obj_rvec, state.obj_t), sel).ravel()

    r0 = residual(base)
    J = np.stack([(residual(base + e) - residual(base - e)) / (2 * s)
                  for e, s in zip(np.diag(steps), steps)], axis=1)
    ok = np.isfinite(r0) & np.isfinite(J).all(1)
    J, r0 = J[ok], r0[ok]
    dof = max(len(r0) - len(base), 1)
    sigma2 = float(r0 @ r0) / dof
    cov = np.linalg.pinv(J.T @ J) * sigma2
    # the camera's centre -R^T t as a function of (rvec, t): its covariance through the chain rule
    pose = base[n_free:]
    Jc = np.stack([(_centre(pose + e) - _centre(pose - e)) / (2 * s)
                   for e, s in zip(np.diag(steps[n_free:]), steps[n_free:])], axis=1)
    cov_c = Jc @ cov[n_free:, n_free:] @ Jc.T
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    named = dict(zip(np.flatnonzero(free), sd[:n_free]))
    return Uncertainty(named.get(0, 0.0), named.get(1, 0.0), named.get(2, 0.0), named.get(3, 0.0), named.get(4, 0.0),
                       float(np.sqrt(np.clip(np.diag(cov_c), 0, None)).max()))


def _centre(pose: np.ndarray) -> np.ndarray:
    return -rotvec_to_matrix(pose[:3]).T @ pose[3:]
