"""Cameras short of tags, placed from the scene texture they share with tag-calibrated cameras.

In the simulated cube53 the four floor cameras at the middle of the floor's edges look into the
table's side: they see one tag, or none. COLMAP registers them, but its poses rest on its own
weakest links and on its alignment to the tags (22 mm off on one of them at 640x360). Here the
cameras the tags already placed do the work instead: SIFT features of the short camera are matched
to every calibrated camera (ratio test, then a fundamental-matrix RANSAC per pair); a feature
matched in two or more calibrated cameras is triangulated from those cameras alone (their poses
are known), and the short camera is resected from these world points (PnP RANSAC). The points then
join the bundle adjustment as fixed world points seen by the short camera, next to any tag corners
it sees. This is a fallback, millimetres rather than tenths: SIFT keypoints move with the
viewpoint by about half a pixel, and the table's banded wood gives few, weak features (3-5 mm on
those four cameras at 640x360, against 0.1-1.1 mm for cameras that see two tags or more).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from manus_core.cameras import CameraRig

from ..triangulation import triangulate
from .tag_edges import UNDISTORT_CRITERIA

RATIO = 0.75           # Lowe's ratio test
MIN_PAIR_MATCHES = 15  # fewer verified matches with one camera: that camera does not share the view
MAX_POINT_PX = 0.7     # triangulated from the calibrated cameras with at most this RMS error
PNP_PX = 2.0           # RANSAC inlier distance of the resection
MIN_POINTS = 12


@dataclass(frozen=True)
class SceneAnchors:
    """World points (N,3) a camera sees at pixels (N,2), and its pose from them (world-to-camera)."""

    points: np.ndarray
    xy: np.ndarray
    pose: np.ndarray  # (4,4)
    matched_cameras: int


def _features(gray: np.ndarray, max_features: int) -> tuple[np.ndarray, np.ndarray]:
    """(xy (N,2), descriptors (N,128)) of SIFT keypoints."""
    kp, des = cv2.SIFT_create(nfeatures=max_features).detectAndCompute(gray, None)
    xy = np.array([k.pt for k in kp], np.float64).reshape(-1, 2)
    return xy, (des if des is not None else np.zeros((0, 128), np.float32))


def _undistorted(xy: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    return cv2.undistortPoints(xy.reshape(-1, 1, 2), K, dist, P=K, criteria=UNDISTORT_CRITERIA).reshape(-1, 2)


def _verified_matches(xy_a, des_a, xy_b, des_b, Ka, da, Kb, db) -> tuple[np.ndarray, np.ndarray]:
    """Indices (ia, ib) of matches that pass the ratio test and the epipolar geometry."""
    if len(des_a) < 2 or len(des_b) < 2:
        return np.zeros(0, int), np.zeros(0, int)
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(des_a, des_b, k=2)  # OpenCV hands matches out as objects
    pairs = np.array([(m[0].queryIdx, m[0].trainIdx) for m in knn
                      if len(m) == 2 and m[0].distance < RATIO * m[1].distance], int).reshape(-1, 2)
    if len(pairs) < MIN_PAIR_MATCHES:
        return np.zeros(0, int), np.zeros(0, int)
    ua, ub = _undistorted(xy_a[pairs[:, 0]], Ka, da), _undistorted(xy_b[pairs[:, 1]], Kb, db)
    _, mask = cv2.findFundamentalMat(ua, ub, cv2.USAC_MAGSAC, 1.0, 0.999)
    if mask is None:
        return np.zeros(0, int), np.zeros(0, int)
    keep = mask.ravel().astype(bool)
    if keep.sum() < MIN_PAIR_MATCHES:
        return np.zeros(0, int), np.zeros(0, int)
    return pairs[keep, 0], pairs[keep, 1]


def scene_anchors(images: dict[str, np.ndarray], calibrated: CameraRig, targets: dict[str, tuple[np.ndarray, np.ndarray]],
                  max_features: int = 4000) -> dict[str, SceneAnchors]:
    """Place each target camera from scene points triangulated by the calibrated cameras.

    images: {camera: grey uint8 image} for the targets and the calibrated cameras (a static scene:
    one frame per camera); calibrated: the cameras already placed; targets: {camera: (K, dist)}.
    Returns the targets that could be placed (enough verified points); the others are left out.
    """
    cams = [c for c in calibrated.ids if c in images]
    if len(cams) < 2 or not targets:
        return {}
    cv2.setRNGSeed(0)  # the RANSACs below: the same input gives the same cameras, whatever ran before
    rig = calibrated.subset(cams)
    feats = {c: _features(images[c], max_features) for c in cams}
    out = {}
    for target, (K, dist) in targets.items():
        if target not in images:
            continue
        xy_t, des_t = _features(images[target], max_features)
        # one row per calibrated camera, one column per feature of the target: where it was matched
        seen = np.full((len(cams), len(xy_t), 3), np.nan)
        partners = 0
        for ci, cam in enumerate(cams):
            i = rig.index(cam)
            xy_c, des_c = feats[cam]
            it, ic = _verified_matches(xy_t, des_t, xy_c, des_c, K, dist, rig.K[i], rig.dist[i])
            if len(it):
                partners += 1
                seen[ci, it, :2] = xy_c[ic]
                seen[ci, it, 2] = 1.0
        usable = np.isfinite(seen[..., 0]).sum(axis=0) >= 2
        if usable.sum() < MIN_POINTS:
            continue
        X, _ = triangulate(rig, seen[:, usable], ransac=True, threshold_px=1.0, max_error_px=MAX_POINT_PX)
        good = np.isfinite(X).all(axis=1)
        X, xy = X[good], xy_t[usable][good]
        if len(X) < MIN_POINTS:
            continue
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(X.reshape(-1, 1, 3), xy.reshape(-1, 1, 2), K, dist,
                                                     iterationsCount=2000, reprojectionError=PNP_PX,
                                                     confidence=0.9999, flags=cv2.SOLVEPNP_EPNP)
        if not ok or inliers is None or len(inliers) < MIN_POINTS:
            continue
        inl = inliers.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(X[inl].reshape(-1, 1, 3), xy[inl].reshape(-1, 1, 2), K, dist, rvec, tvec)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        out[target] = SceneAnchors(X[inl], xy[inl], T, partners)
    return out
