"""The pose of a planar target (a board, or tags on the walls) from its points in one camera."""

from __future__ import annotations

import cv2
import numpy as np


def solve_pnp(obj: np.ndarray, img: np.ndarray, K: np.ndarray, dist: np.ndarray,
              groups: np.ndarray | None = None, ransac_px: float = 4.0
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
    """Pose (rvec, tvec) of points obj seen at img, the inlier mask, and the inlier RMS.

    Without groups the points are one planar target, solved by IPPE (which returns both poses a
    planar target allows; the better one is kept). With groups (one label per point, e.g. the tag
    id), each group of >= 4 points proposes a pose by IPPE, the pose with most points within
    ransac_px wins and is refined on its inliers: a RANSAC over whole tags, so one mis-decoded or
    moved tag cannot pull the pose, and planar minimal sets never reach a general PnP solver.
    """
    obj = np.ascontiguousarray(obj, np.float64).reshape(-1, 3)
    img = np.ascontiguousarray(img, np.float64).reshape(-1, 2)
    labels = np.zeros(len(obj), int) if groups is None else np.asarray(groups)
    best = None
    for g in np.unique(labels):
        sel = labels == g
        if len(np.unique(obj[sel], axis=0)) < 4:  # repeated frames of fewer corners fit any pose
            continue
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj[sel].reshape(-1, 1, 3), img[sel].reshape(-1, 1, 2), K, dist,
                                                    flags=cv2.SOLVEPNP_IPPE)
        for rvec, tvec in zip(rvecs[:n], tvecs[:n]):
            proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
            err = np.linalg.norm(proj.reshape(-1, 2) - img, axis=1)
            inl = err < (ransac_px if groups is not None else np.inf)
            score = (inl.sum(), -np.sum(np.minimum(err, ransac_px) ** 2))
            if best is None or score > best[0]:
                best = (score, rvec, tvec, inl)
    if best is None or best[3].sum() < 4:
        return None
    _, rvec, tvec, inliers = best
    for _ in range(2):  # refine, then re-collect the inliers of the refined pose once
        rvec, tvec = cv2.solvePnPRefineLM(obj[inliers].reshape(-1, 1, 3), img[inliers].reshape(-1, 1, 2), K, dist,
                                          rvec, tvec)
        if groups is None:
            break
        proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
        inliers = np.linalg.norm(proj.reshape(-1, 2) - img, axis=1) < ransac_px
        if inliers.sum() < 4:
            return None
    proj, _ = cv2.projectPoints(obj[inliers], rvec, tvec, K, dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img[inliers]) ** 2, axis=1))))
    return rvec.ravel(), tvec.ravel(), inliers, rms
