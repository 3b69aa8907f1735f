"""Extrinsics of static cameras from tags on the walls (MANUS cube).

Every camera sees tags whose corners are known in the world frame (tags.json). Each camera's pose
comes from PnP with a RANSAC over whole tags; then one bundle adjustment refines all cameras
together, and optionally the tags themselves (a printed layout measured to a few millimetres)
under a prior to the layout. Cameras short of tags are placed afterwards, from scene points or a
COLMAP pose, and adjusted with the others held where the tags put them.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable

import cv2
import numpy as np

from manus_core.cameras import CameraRig
from manus_core.errors import ExtrinsicsError, UnplacedCamerasError
from manus_core.rotations import matrix_to_rotvec, rotation_angle_deg, rotvec_to_matrix

from .boards import TagLayout
from .bundle import (
    N_INTRINSICS,
    BundleResult,
    BundleState,
    Observations,
    bundle_adjust,
    pack_intrinsics,
    project_points,
    residuals_of,
    unpack_intrinsics,
)
from .detect import Detection
from .pnp import solve_pnp
from .result import RigCalibration, camera_stats, require_all, rig_from_state
from .tag_intrinsics import uncertainty

MIN_TAG_POINTS = 8  # two tags: PnP with a margin against one mis-decoded tag

# (the tag-placed cameras, {camera: (K, dist)}) -> {camera: features.SceneAnchors}
SceneCallback = Callable[[CameraRig, dict[str, tuple[np.ndarray, np.ndarray]]], dict]


def calibrate_tag_rig(detections: dict[str, dict[int, Detection]], sizes: dict[str, tuple[int, int]],
                      layout: TagLayout, intrinsics: dict[str, tuple[np.ndarray, np.ndarray]],
                      refine_intrinsics: bool = False, refine_tags: bool = False, tag_sigma_m: float = 0.002,
                      allow_partial: bool = False, ransac_px: float = 4.0,
                      initial_poses: dict[str, np.ndarray] | None = None,
                      scene: SceneCallback | None = None,
                      free_intrinsics: dict[str, np.ndarray] | None = None) -> RigCalibration:
    """Calibrate static cameras from tags on the walls (tags.json, world frame).

    detections: {camera: {frame: Detection}} with tag point ids (tag_id * 4 + corner);
    intrinsics: {camera: (K, dist)}. refine_tags: each tag also moves (rigidly), held to the
    layout by a prior of tag_sigma_m metres (and the matching angle), for layouts measured by hand.
    Cameras whose tags are too few for PnP are placed after the others:
    scene: (the tag-placed cameras, {camera: (K, dist)}) -> {camera: features.SceneAnchors}; each
      such camera is resected from scene points the placed cameras triangulate, and adjusted on
      those points and whatever tag corners it sees (rig.py passes features.scene_anchors);
    initial_poses: {camera: (4,4) world-to-camera} (from COLMAP) for those the scene does not place.
    free_intrinsics: {camera: (9,) bool} the intrinsics each camera's adjustment estimates (the
      model its tags constrain, tag_intrinsics); extra["intrinsics"] then gives their standard
      deviations and the camera's position's, and what its data leaves loose.
    """
    pid, world = layout.points()
    lookup = {int(p): i for i, p in enumerate(pid)}
    names = list(detections)
    problems: dict[str, str] = {}
    placed: dict[str, np.ndarray] = {}
    pnp_rms: dict[str, float] = {}
    short: dict[str, tuple[str, np.ndarray, np.ndarray]] = {}  # camera -> (why, known point ids, pixels)
    for name in names:
        if name not in intrinsics:
            problems[name] = "no intrinsics"
            continue
        dets = list(detections[name].values())
        ids = np.concatenate([d.ids for d in dets]) if dets else np.zeros(0, int)
        xy = np.concatenate([d.xy for d in dets]) if dets else np.zeros((0, 2))
        known = np.array([i in lookup for i in ids.tolist()], bool)
        n_tags = len(np.unique(ids[known] // 4))
        # distinct corners: the frames of a static camera repeat the same few
        if len(np.unique(ids[known])) < MIN_TAG_POINTS:
            other = np.setdiff1d(np.unique(ids // 4), layout.ids)
            why = (f"sees no tag of {layout.source}" if n_tags == 0 else
                   f"sees only {len(np.unique(ids[known]))} corner(s) of {n_tags} tag(s) of {layout.source}, "
                   f"needs {MIN_TAG_POINTS} ({MIN_TAG_POINTS // 4} whole tags)")
            if len(other):
                why += f" (it sees tags {other[:10].tolist()}, which the layout does not list)"
            short[name] = (why, ids[known], xy[known])
            continue
        K, dist = intrinsics[name]
        obj = world[[lookup[i] for i in ids[known].tolist()]]
        out = solve_pnp(obj, xy[known], K, dist, groups=ids[known] // 4, ransac_px=ransac_px)
        if out is None:
            problems[name] = f"tag PnP failed ({n_tags} tags): the intrinsics or the tag layout do not fit"
            continue
        T = np.eye(4)
        T[:3, :3] = rotvec_to_matrix(out[0])
        T[:3, 3] = out[1]
        placed[name] = T
        pnp_rms[name] = out[3]
    if not placed:
        require_all(names, {**problems, **{n: s[0] for n, s in short.items()}}, allow_partial,
                    UnplacedCamerasError)
        raise ExtrinsicsError("no camera could be placed from the tags")
    cams = [n for n in names if n in placed]
    obs, pidx = _tag_observations(detections, cams, lookup)
    obs, obj_rvec, obj_t, prior = _tag_objects(obs, pidx, world, layout, refine_tags, tag_sigma_m)
    camT = np.array([placed[n] for n in cams])
    state = BundleState(np.array([pack_intrinsics(*intrinsics[n]) for n in cams]),
                        matrix_to_rotvec(camT[:, :3, :3]), camT[:, :3, 3].copy(), obj_rvec, obj_t)
    imask = np.ones((len(cams), N_INTRINSICS), bool) if refine_intrinsics else None
    if free_intrinsics:
        imask = np.array([free_intrinsics.get(n, np.zeros(N_INTRINSICS, bool)) for n in cams])
    result = bundle_adjust(state, obs, np.zeros(len(cams), bool), np.full(len(obj_t), not refine_tags), imask,
                           obj_prior=prior)
    extra = {"pnp_rms_px": pnp_rms, "ba_rms_before_px": result.cost_initial_px}
    if free_intrinsics:
        extra["intrinsics"] = _uncertainties(result, cams, free_intrinsics, sizes)
    if refine_tags:
        moved = np.linalg.norm(result.state.obj_t - obj_t, axis=1)
        extra["tag_shift_m"] = {int(t): float(m) for t, m in zip(layout.ids, moved)}
    anchors, late = {}, {}
    if short and scene is not None:
        first = rig_from_state(cams, result.state, np.array([sizes[n] for n in cams]))
        anchors = scene(first, {n: intrinsics[n] for n in short})
    for name, (why, ids_k, xy_k) in short.items():
        if name in anchors:
            late[name] = anchors[name].pose
        elif initial_poses and name in initial_poses:
            late[name] = _single_tag_pose(ids_k, world[[lookup[i] for i in ids_k.tolist()]], xy_k,
                                          intrinsics.get(name), initial_poses[name])
        else:
            problems[name] = why
    require_all(names, problems, allow_partial, UnplacedCamerasError)
    outliers = result.outliers
    if late:
        result = _adjust_late(result, cams, late, anchors, detections, lookup, world, layout, refine_tags,
                              intrinsics, int(pid.max()) + 1)
        outliers += result.outliers
        cams = cams + list(late)
        extra["scene_points"] = {n: {"points": len(a.points), "cameras": a.matched_cameras} for n, a in anchors.items()}
        extra["colmap_poses"] = [n for n in late if n not in anchors]
    size_arr = np.array([sizes[n] for n in cams])
    stats = camera_stats(tuple(cams), result.obs, result.residuals, size_arr)
    rig = rig_from_state(cams, result.state, size_arr, stats)
    return RigCalibration(rig, "tags", stats, result.obs, result.residuals, outliers,
                          partial=bool(problems), missing=problems, extra=extra)


def _uncertainties(result: BundleResult, cams: list[str], free: dict[str, np.ndarray],
                   sizes: dict[str, tuple[int, int]]) -> dict[str, dict]:
    """Per camera whose intrinsics were estimated: their standard deviations and its position's
    from the adjustment, and what they leave loose (tag_intrinsics.Uncertainty.weak)."""
    out = {}
    for c, name in enumerate(cams):
        if name not in free:
            continue
        sd = uncertainty(result.state, result.obs, c, free[name])
        K = unpack_intrinsics(result.state.intr[c])[0]
        out[name] = {"sd": {"fx": sd.fx, "fy": sd.fy, "cx": sd.cx, "cy": sd.cy, "k1": sd.k1,
                            "centre_mm": sd.centre_m * 1000}, "weak": sd.weak(K, sizes[name][0])}
    return out


def _tag_objects(obs: Observations, pidx: np.ndarray, world: np.ndarray, layout: TagLayout, refine_tags: bool,
                 tag_sigma_m: float) -> tuple[Observations, np.ndarray, np.ndarray, tuple | None]:
    """The rigid objects tag corners belong to: the world (one fixed object), or with refine_tags
    each tag on its own, starting at (and held near by a prior) its layout pose."""
    if refine_tags:
        centre = layout.corners.mean(axis=1)
        obj_rvec, obj_t = np.zeros((len(layout.ids), 3)), centre.copy()
        obs = replace(obs, obj=pidx // 4, local=world[pidx] - centre[pidx // 4])
        return obs, obj_rvec, obj_t, (obj_rvec.copy(), obj_t.copy(), tag_sigma_m / layout.size, tag_sigma_m)
    return replace(obs, obj=np.zeros(len(pidx), int), local=world[pidx]), np.zeros((1, 3)), np.zeros((1, 3)), None


def _adjust_late(first: BundleResult, cams: list[str], late: dict[str, np.ndarray], anchors: dict,
                 detections, lookup, world, layout, refine_tags, intrinsics, first_scene_id: int) -> BundleResult:
    """Adjust the cameras placed after the tag adjustment (scene points, COLMAP), the others held
    where the tags put them. Scene points are fixed world points (one more object, the identity);
    their point ids start at first_scene_id, their frame is -1."""
    every = cams + list(late)
    obs, pidx = _tag_observations(detections, every, lookup)
    obs, _, _, _ = _tag_objects(obs, pidx, world, layout, refine_tags, 0.0)
    obs = replace(obs, weight=np.ones(len(obs)))
    world_obj = len(first.state.obj_t)
    # inverse-error weights: tag corners fit to hundredths of a pixel, scene features to tenths, so
    # a camera's few tag corners must not be outvoted by its many scene points. The tags are
    # weighted up rather than the scene down: the robust loss keeps its scale (pixels) for the
    # scene points, which are the ones with outliers.
    tag_rms = float(np.sqrt(np.nanmean(np.sum(first.residuals**2, axis=1))))
    rows, next_id = [obs], first_scene_id
    for name, a in anchors.items():
        if name not in late:
            continue
        n, c = len(a.points), every.index(name)
        rms = float(np.sqrt(np.mean(np.sum((_project_pose(a.points, a.pose, intrinsics[name]) - a.xy) ** 2, axis=1))))
        obs.weight[obs.cam == c] = max(1.0, rms / max(tag_rms, 1e-9))
        rows.append(Observations(np.full(n, c), np.full(n, world_obj), a.points, a.xy,
                                 np.arange(next_id, next_id + n), np.full(n, -1), np.ones(n)))
        next_id += n
    obs = Observations(*(np.concatenate([getattr(r, f) for r in rows]) for f in
                         ("cam", "obj", "local", "xy", "point", "frame", "weight")))
    lateT = np.array(list(late.values()))
    s = first.state
    state = BundleState(np.concatenate([s.intr, [pack_intrinsics(*intrinsics[n]) for n in late]]),
                        np.concatenate([s.cam_rvec, matrix_to_rotvec(lateT[:, :3, :3])]),
                        np.concatenate([s.cam_t, lateT[:, :3, 3]]),
                        np.concatenate([s.obj_rvec, np.zeros((1, 3))]), np.concatenate([s.obj_t, np.zeros((1, 3))]))
    # a late camera that nothing here sees (no tag, no scene point) keeps its COLMAP pose
    free = np.isin(np.arange(len(every)), obs.cam) & (np.arange(len(every)) >= len(cams))
    return bundle_adjust(state, obs, ~free, np.ones(world_obj + 1, bool))


def _project_pose(X: np.ndarray, pose: np.ndarray, intr: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """World points (N,3) to distorted pixels (N,2) of one camera (world-to-camera pose (4,4))."""
    Xc = X @ pose[:3, :3].T + pose[:3, 3]
    return project_points(Xc, np.broadcast_to(pack_intrinsics(*intr), (len(X), N_INTRINSICS)))


def _single_tag_pose(pid: np.ndarray, obj: np.ndarray, img: np.ndarray, intr, rough: np.ndarray) -> np.ndarray:
    """A camera with one tag in view and a rough pose (from COLMAP): of the two poses a single
    planar tag allows (IPPE), the one nearer the rough pose in rotation; the rough pose itself
    when no tag is seen whole."""
    tags, counts = np.unique(np.unique(pid) // 4, return_counts=True)  # distinct corners per tag
    if intr is None or not (counts >= 4).any():
        return rough
    sel = pid // 4 == tags[np.argmax(counts >= 4)]
    n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj[sel].reshape(-1, 1, 3), img[sel].reshape(-1, 1, 2), intr[0], intr[1],
                                             flags=cv2.SOLVEPNP_IPPE)
    if n == 0:
        return rough
    Rs = rotvec_to_matrix(np.array(rvecs).reshape(-1, 3))
    best = int(np.argmin(rotation_angle_deg(Rs, rough[None, :3, :3])))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rs[best], np.ravel(tvecs[best])
    return T


def _tag_observations(detections: dict[str, dict[int, Detection]], cams: list[str], lookup: dict[int, int]
                      ) -> tuple[Observations, np.ndarray]:
    """Observations of the layout's tag corners (world frame, object 0) and their layout indices."""
    rows = []
    for c, n in enumerate(cams):
        for f, d in detections.get(n, {}).items():
            sel = np.array([i in lookup for i in d.ids.tolist()], bool)
            if sel.any():
                rows.append((c, f, d.ids[sel], d.xy[sel]))
    if not rows:
        raise ExtrinsicsError("no camera sees a tag of the layout")
    pidx = np.concatenate([[lookup[i] for i in r[2].tolist()] for r in rows]).astype(int)
    obs = Observations(cam=np.concatenate([np.full(len(r[2]), r[0]) for r in rows]), obj=np.zeros(len(pidx), int),
                       local=np.zeros((len(pidx), 3)), xy=np.concatenate([r[3] for r in rows]),
                       point=np.concatenate([r[2] for r in rows]),
                       frame=np.concatenate([np.full(len(r[2]), r[1]) for r in rows]))
    return obs, pidx


def evaluate_tag_rig(rig: CameraRig, detections: dict[str, dict[int, Detection]], layout: TagLayout,
                     method: str, extra: dict | None = None) -> RigCalibration:
    """Reprojection statistics of a given rig on the tag corners it sees (no adjustment)."""
    pid, world = layout.points()
    lookup = {int(p): i for i, p in enumerate(pid)}
    obs, pidx = _tag_observations(detections, list(rig.ids), lookup)
    obs = replace(obs, local=world[pidx])
    state = BundleState(pack_intrinsics(rig.K, rig.dist), matrix_to_rotvec(rig.R), rig.t.copy(),
                        np.zeros((1, 3)), np.zeros((1, 3)))
    res = residuals_of(state, obs)
    stats = camera_stats(rig.ids, obs, res, rig.size)
    out = CameraRig(rig.ids, rig.K, rig.dist, rig.R, rig.t, rig.size, [stats[i].rms_px for i in rig.ids])
    return RigCalibration(out, method, stats, obs, res, 0, extra=extra or {})
