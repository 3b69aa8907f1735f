"""Extrinsics by structure from motion (pycolmap 4.x), put into the tag world frame.

One image per camera (the cameras are static, so more frames of the same camera add nothing but
noise) goes through COLMAP's SIFT features, exhaustive matching and incremental mapping with every
camera's intrinsics held fixed (FULL_OPENCV with k4..k6 = 0 is exactly the OpenCV 5-coefficient
model). COLMAP's frame has an arbitrary origin, orientation and scale; the tag corners seen by the
cameras are triangulated in it and matched to tags.json, and a similarity (Umeyama, with outlier
tags dropped) brings every camera into the world frame in metres.
COLMAP registers cameras that see no tag at all, as long as they share texture with the others:
that is what it adds to the tag method.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import cv2
import numpy as np
import pycolmap  # after cv2: a process that loads pycolmap's zlib first aborts in cv2's PNG writer

from manus_core.cameras import CameraRig
from manus_core.errors import ColmapError

from ..triangulation import triangulate
from .boards import TagLayout
from .detect import Detection


def colmap_poses(images: dict[str, np.ndarray], intrinsics: dict[str, tuple[np.ndarray, np.ndarray]],
                 workdir: str | Path | None = None, max_features: int = 4096, threads: int = -1
                 ) -> tuple[dict[str, np.ndarray], dict]:
    """World(COLMAP)-to-camera transforms (4,4) of the cameras COLMAP registers, and statistics.

    images: {camera: one image (grey or BGR uint8)}; intrinsics: {camera: (K (3,3), dist (5,))}.
    """
    with tempfile.TemporaryDirectory(prefix="colmap-", dir=workdir) as tmp:
        tmp = Path(tmp)
        image_dir = tmp / "images"
        image_dir.mkdir()
        names = {}
        for cam, image in images.items():
            name = f"{cam}.bmp"  # BMP: cv2's PNG writer aborts when pycolmap's zlib was loaded first
            if not cv2.imwrite(str(image_dir / name), image):
                raise ColmapError(f"camera {cam}: cannot write its image for COLMAP")
            names[name] = cam
        return _run(tmp, image_dir, names, intrinsics, max_features, threads)


def _run(tmp: Path, image_dir: Path, names: dict[str, str], intrinsics, max_features: int, threads: int):
    pycolmap.set_random_seed(0)  # the same input gives the same model (RANSAC and sampling are seeded)
    db_path = tmp / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "FULL_OPENCV"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = max_features
    extraction.num_threads = threads
    pycolmap.extract_features(db_path, image_dir, image_names=sorted(names), camera_mode=pycolmap.CameraMode.PER_IMAGE,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
    # Every image has its own camera: give each the calibrated intrinsics before matching.
    db = pycolmap.Database.open(db_path)
    try:
        for image in db.read_all_images():
            cam = db.read_camera(image.camera_id)
            K, dist = intrinsics[names[image.name]]
            d = np.asarray(dist, float).ravel()[:5]
            cam.params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2], d[0], d[1], d[2], d[3], d[4], 0.0, 0.0, 0.0]
            cam.has_prior_focal_length = True
            db.update_camera(cam)
    finally:
        db.close()
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    pycolmap.match_exhaustive(db_path, matching_options=matching, device=pycolmap.Device.cpu)
    options = pycolmap.IncrementalPipelineOptions()
    options.ba_refine_focal_length = False
    options.ba_refine_principal_point = False
    options.ba_refine_extra_params = False
    options.mapper.abs_pose_refine_focal_length = False
    options.mapper.abs_pose_refine_extra_params = False
    options.multiple_models = False
    options.random_seed = 0
    options.num_threads = threads
    options.min_model_size = 3
    recs = pycolmap.incremental_mapping(db_path, image_dir, tmp / "sparse", options=options)
    if not recs:
        raise ColmapError(f"COLMAP registered no cameras ({len(names)} images): the views share too little "
                          f"texture; use --method tags")
    rec = max(recs.values(), key=lambda r: r.num_reg_images())
    poses = {}
    for image in rec.images.values():
        if not image.has_pose:
            continue
        pose = image.cam_from_world()
        T = np.eye(4)
        T[:3, :3] = pose.rotation.matrix()
        T[:3, 3] = pose.translation
        poses[names[image.name]] = T
    stats = {"registered": len(poses), "images": len(names), "points3D": rec.num_points3D(),
             "mean_reprojection_px": float(rec.compute_mean_reprojection_error())}
    return poses, stats


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Umeyama: (s, R, t) minimizing |dst - (s R src + t)|^2 over point pairs (N,3)."""
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (a**2).sum(axis=1).mean())
    return s, R, md - s * R @ ms


def align_to_tags(poses: dict[str, np.ndarray], intrinsics: dict[str, tuple[np.ndarray, np.ndarray]],
                  sizes: dict[str, tuple[int, int]], tag_detections: dict[str, Detection], layout: TagLayout
                  ) -> tuple[CameraRig, dict]:
    """Move COLMAP cameras into the world frame of tags.json, in metres.

    tag_detections: {camera: Detection of tag points} (one frame per camera is enough). Tag corners
    seen by >= 2 registered cameras are triangulated in COLMAP's frame and matched to the layout;
    tags whose corners stay more than 3 x the median off after a first fit are dropped.
    """
    cams = [c for c in poses if c in intrinsics]
    rig = CameraRig(tuple(cams), [intrinsics[c][0] for c in cams], [intrinsics[c][1] for c in cams],
                    [poses[c][:3, :3] for c in cams], [poses[c][:3, 3] for c in cams], [sizes[c] for c in cams])
    pid, world = layout.points()
    lookup = {int(p): i for i, p in enumerate(pid)}
    pts = np.full((len(cams), len(pid), 3), np.nan)
    for ci, cam in enumerate(cams):
        det = tag_detections.get(cam)
        if det is None:
            continue
        known = np.array([i in lookup for i in det.ids.tolist()], bool)
        idx = [lookup[i] for i in det.ids[known].tolist()]
        pts[ci, idx, :2] = det.xy[known]
        pts[ci, idx, 2] = 1.0
    seen = np.isfinite(pts[..., 0]).sum(axis=0) >= 2
    if seen.sum() < 8:
        raise ColmapError(f"only {int(seen.sum())} tag corners are seen by two registered cameras; at least 8 "
                          f"(two tags) are needed to put the COLMAP model into the world frame of {layout.source}")
    X, err = triangulate(rig, pts[:, seen], ransac=True, threshold_px=4.0)
    good = np.isfinite(X).all(axis=1)
    src, dst, tag = X[good], world[seen][good], (pid[seen][good] // 4)
    keep = np.ones(len(src), bool)
    for _ in range(2):
        s, R, t = similarity(src[keep], dst[keep])
        resid = np.linalg.norm(dst - (s * src @ R.T + t), axis=1)
        bad_tags = np.unique(tag[resid > max(3 * np.median(resid[keep]), 0.002)])
        keep = ~np.isin(tag, bad_tags)
        if keep.sum() < 8:
            raise ColmapError(f"the tags seen by the COLMAP cameras do not agree with {layout.source} "
                              f"(median misfit {np.median(resid) * 1000:.1f} mm)")
    s, R, t = similarity(src[keep], dst[keep])
    resid = np.linalg.norm(dst[keep] - (s * src[keep] @ R.T + t), axis=1)
    # x_world = s R x_colmap + t  =>  x_cam (metres) = Rc R^T (x_world - t) + s tc
    Rw = rig.R @ R.T
    tw = s * rig.t - np.einsum("cij,j->ci", Rw, t)
    aligned = CameraRig(rig.ids, rig.K, rig.dist, Rw, tw, rig.size)
    info = {"scale": s, "tag_corners_used": int(keep.sum()), "tags_dropped": [int(x) for x in np.unique(tag[~keep])],
            "alignment_rms_mm": float(np.sqrt(np.mean(resid**2)) * 1000)}
    return aligned, info
