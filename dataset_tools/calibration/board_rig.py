"""Extrinsics from a board waved through the volume (caliscope-style).

In each synchronized frame the board is seen by some cameras. Board poses from PnP give
camera-to-camera transforms, chained over a maximum spanning tree of the cameras that see the
board together; then one bundle adjustment of every camera's pose and intrinsics and every
frame's board pose.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from manus_core.errors import ExtrinsicsError, IntrinsicsError
from manus_core.rotations import matrix_to_rotvec, mean_rotation, rotation_angle_deg, rotvec_to_matrix

from .boards import Board
from .bundle import N_INTRINSICS, BundleState, Observations, bundle_adjust, pack_intrinsics
from .detect import Detection
from .intrinsics import Intrinsics, calibrate_intrinsics
from .pnp import solve_pnp
from .result import RigCalibration, camera_stats, require_all, rig_from_state


def calibrate_board_rig(detections: dict[str, dict[int, Detection]], sizes: dict[str, tuple[int, int]],
                        board: Board, intrinsics: dict[str, Intrinsics | tuple[np.ndarray, np.ndarray]] | None = None,
                        refine_intrinsics: bool = True, fix_k3: bool = False, allow_partial: bool = False,
                        pnp_max_px: float = 3.0, loss_scale_px: float = 1.0) -> RigCalibration:
    """Calibrate cameras that saw one board in synchronized frames.

    detections: {camera: {sync index: Detection}}; the same sync index in two cameras means the
    same instant. intrinsics: {camera: Intrinsics or (K, dist)} to start from (computed here from
    the same detections where missing). The world frame is the board in the frame where most
    cameras see it (x along the board's columns, y along its rows, z out of the board's back).
    """
    if board.type == "chessboard":
        raise ExtrinsicsError(f"{board.source}: a chessboard looks the same turned by 180 degrees, so "
                              f"cameras cannot agree on its corners; use a charuco or apriltag-grid board")
    names = list(detections)
    problems: dict[str, str] = {}
    K0, d0, intr_info = {}, {}, {}
    for name in names:
        given = (intrinsics or {}).get(name)
        if given is None:
            try:
                given = calibrate_intrinsics(detections[name], board, sizes[name], camera=name, fix_k3=fix_k3)
            except IntrinsicsError as exc:
                problems[name] = exc.reason
                continue
        if isinstance(given, Intrinsics):
            K0[name], d0[name], intr_info[name] = given.K, given.dist, given.summary()
        else:
            K0[name], d0[name] = np.asarray(given[0], float), np.asarray(given[1], float).ravel()[:5]
    obj_pts = board.object_points()
    # Board pose in each camera and frame (only views that PnP fits well).
    poses: dict[str, dict[int, np.ndarray]] = {}
    for name in K0:
        poses[name] = {}
        for f, det in detections[name].items():
            if len(det) < 6:
                continue
            out = solve_pnp(obj_pts[det.ids], det.xy, K0[name], d0[name])
            if out is not None and out[3] <= pnp_max_px:
                T = np.eye(4)
                T[:3, :3] = rotvec_to_matrix(out[0])
                T[:3, 3] = out[1]
                poses[name][f] = T
    placed = _chain_cameras({n: p for n, p in poses.items() if p}, problems)
    if not placed:
        raise ExtrinsicsError("no two cameras see the board in the same frame: " + "; ".join(
            f"{n}: {m}" for n, m in problems.items()) if problems else "no camera sees the board")
    require_all(names, problems, allow_partial)
    cams = [n for n in names if n in placed]
    ci = {n: i for i, n in enumerate(cams)}
    # One object per frame seen by a placed camera; its pose from the camera seeing most points.
    frames = sorted({f for n in cams for f in poses[n]})
    fi = {f: i for i, f in enumerate(frames)}
    obj_T = np.zeros((len(frames), 4, 4))
    best_count = np.zeros(len(frames))
    for n in cams:
        for f, T in poses[n].items():
            k = len(detections[n][f])
            if k > best_count[fi[f]]:
                best_count[fi[f]] = k
                obj_T[fi[f]] = np.linalg.inv(placed[n]) @ T
    rows = [(ci[n], fi[f], det) for n in cams for f, det in detections[n].items() if f in fi]
    obs = Observations(
        cam=np.concatenate([np.full(len(d), c) for c, _, d in rows]),
        obj=np.concatenate([np.full(len(d), o) for _, o, d in rows]),
        local=np.concatenate([obj_pts[d.ids] for _, _, d in rows]),
        xy=np.concatenate([d.xy for _, _, d in rows]),
        point=np.concatenate([d.ids for _, _, d in rows]),
        frame=np.concatenate([np.full(len(d), frames[o]) for _, o, d in rows]))
    camT = np.array([placed[n] for n in cams])
    state = BundleState(np.array([pack_intrinsics(K0[n], d0[n]) for n in cams]),
                        matrix_to_rotvec(camT[:, :3, :3]), camT[:, :3, 3].copy(),
                        matrix_to_rotvec(obj_T[:, :3, :3]), obj_T[:, :3, 3].copy())
    ref = int(np.argmax([len(poses[n]) for n in cams]))
    fixed_cams = np.zeros(len(cams), bool)
    fixed_cams[ref] = True
    imask = None
    if refine_intrinsics:
        imask = np.ones((len(cams), N_INTRINSICS), bool)
        if fix_k3:
            imask[:, 8] = False
    result = bundle_adjust(state, obs, fixed_cams, np.zeros(len(frames), bool), imask,
                           loss_scale_px=loss_scale_px)
    # World frame: the board in the frame most cameras saw.
    counts = np.bincount(result.obs.obj, minlength=len(frames))
    views = np.array([len(np.unique(result.obs.cam[result.obs.obj == o])) for o in range(len(frames))])
    origin = int(np.lexsort((counts, views))[-1])
    state = _move_world(result.state, rotvec_to_matrix(result.state.obj_rvec[origin]), result.state.obj_t[origin])
    size_arr = np.array([sizes[n] for n in cams])
    stats = camera_stats(tuple(cams), result.obs, result.residuals, size_arr)
    stats = {n: replace(s, intrinsics=intr_info.get(n, {})) for n, s in stats.items()}
    rig = rig_from_state(cams, state, size_arr, stats)
    return RigCalibration(rig, "board", stats, result.obs, result.residuals, result.outliers,
                          partial=bool(problems), missing=problems,
                          extra={"world_frame": f"board in frame {frames[origin]}",
                                 "frames": len(frames), "ba_rms_before_px": result.cost_initial_px})


def _move_world(state: BundleState, R: np.ndarray, t: np.ndarray) -> BundleState:
    """New world frame whose pose in the old world is (R, t): x_old = R x_new + t."""
    Rc = rotvec_to_matrix(state.cam_rvec)
    Ro = rotvec_to_matrix(state.obj_rvec)
    return BundleState(state.intr.copy(), matrix_to_rotvec(Rc @ R), np.einsum("cij,j->ci", Rc, t) + state.cam_t,
                       matrix_to_rotvec(R.T @ Ro), (state.obj_t - t) @ R)


def _chain_cameras(poses: dict[str, dict[int, np.ndarray]], problems: dict[str, str]) -> dict[str, np.ndarray]:
    """World(=reference camera)-to-camera transforms from board poses seen in shared frames.

    The reference is the camera sharing most frames with the others; cameras are added along a
    maximum spanning tree (most shared frames first); each edge is a robust mean of the per-frame
    relative poses. Cameras that share no frame with the tree are reported in `problems`.
    """
    names = list(poses)
    shared = {(a, b): sorted(set(poses[a]) & set(poses[b])) for a in names for b in names if a != b}
    weight = {n: sum(len(shared[(n, m)]) for m in names if m != n) for n in names}
    if not names:
        return {}
    ref = max(names, key=lambda n: weight[n])
    placed = {ref: np.eye(4)}
    while True:
        edges = [(len(shared[(a, b)]), a, b) for a in placed for b in names if b not in placed and shared[(a, b)]]
        if not edges:
            break
        _, a, b = max(edges)
        # T_b<-a from each shared frame: T_b<-board @ inv(T_a<-board)
        rel = np.array([poses[b][f] @ np.linalg.inv(poses[a][f]) for f in shared[(a, b)]])
        R = mean_rotation(rel[:, :3, :3])
        ang = rotation_angle_deg(rel[:, :3, :3], R[None])
        keep = ang <= max(3 * np.median(ang), 1.0)
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = np.median(rel[keep, :3, 3], axis=0)
        placed[b] = T @ placed[a]
    for n in names:
        if n not in placed:
            problems[n] = "never sees the board in the same frame as the other cameras"
    return placed
