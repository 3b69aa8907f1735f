"""Bundle adjustment: the project's Levenberg-Marquardt against scipy and pycolmap on one problem.

    .venv/bin/python benchmarks/bundle_solvers.py [--quick] [--repeats N]

(bench_calibration.py runs it too, as part of `make bench`.)

The problem (no images are rendered): the 53 true cameras of the simulated cube (1280x720, seed 1)
look at the 1616 corners of a dense tag layout (8x8 tags of 9 cm per wall, and the table's sides). Every corner a
camera sees (in the image, in front of it) is observed with 0.05 px Gaussian noise (a detector's
precision), and 1 % of the observations are gross outliers (3..8 px off); corners seen by one
camera only are left out (COLMAP refuses them). Every camera starts perturbed, each amount in a
random direction or sign: pose by 1 deg and 2 cm, fx and fy by 1 %, cx and cy by 3 px, k1 by 0.02,
k2 by 0.005, p1 and p2 by 3e-4. The tags are the fixed world (one object, the identity, as
tag_rig.py poses it); free are each camera's pose and fx fy cx cy k1 k2 p1 p2 (k3 is 0 and held).

Solvers, from the same start, with a soft-L1 loss of scale 1 px:
  own       dataset_tools.calibration.bundle.bundle_adjust (LM + one outlier-removal pass and re-solve)
  scipy     least_squares(method="trf", loss="soft_l1", jac_sparsity=camera blocks, x_scale="jac");
            its soft-L1 acts on each of x and y apart, the others' on the 2D error of an observation
  pycolmap  COLMAP's Ceres bundle adjuster, one OPENCV camera and one image per camera, every
            tag corner a constant 3D point, loss SOFT_L1, Ceres' default stopping rules
  pycolmap+pass  the same, then own's outlier rule (max(4 px, 5 x median)) and a second solve
Time is the best of N runs (default 3), pycolmap's including the building of its Reconstruction
from the start (~25 ms at 53 cameras); BLAS, OpenMP and Ceres are held to one thread so that no
solver gets more cores than another. Errors: RMS reprojection error (px) on the true inliers (the
observations not made gross outliers), and against the truth: camera centre (mm), rotation (deg),
focal length fx and fy (%), principal point (px). Iterations: own's LM steps (both passes),
scipy's Jacobian evaluations, Ceres' iterations.
"""

from __future__ import annotations

import os

# before numpy loads: one thread for every solver, whatever the machine
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2  # noqa: F401  before pycolmap: a process that loads pycolmap's zlib first aborts in cv2's PNG writer
import numpy as np
import pycolmap
from scipy.optimize import least_squares
from scipy.sparse import csr_matrix

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dataset_tools.calibration.boards import tags_from_dict
from dataset_tools.calibration.bundle import BundleState, Observations, bundle_adjust, pack_intrinsics, residuals_of
from manus_core.cameras import CameraRig
from manus_core.rotations import matrix_to_quat, matrix_to_rotvec, quat_to_matrix, rotation_angle_deg, rotvec_to_matrix
from rig.layouts import make_rig
from rig.sim.cube import true_cameras
from rig.sim.world import World

N_FREE = 8  # fx fy cx cy k1 k2 p1 p2 (k3 held)
LOSS_PX = 1.0


@dataclass(frozen=True)
class Problem:
    truth: CameraRig
    start: BundleState
    obs: Observations
    inlier: np.ndarray  # (M,) bool: not a gross outlier


def make_problem(cameras: int | None, seed: int = 7) -> Problem:
    truth = true_cameras(make_rig(resolution=(1280, 720), seed=1, cameras=cameras))
    pid, X = tags_from_dict(World(tags_per_wall=8, tag_size=0.09, table_tags=True).tags_json()).points()
    uv = truth.project(X)                                   # (C,N,2), NaN behind a camera
    Xc = truth.to_camera(X)
    with np.errstate(divide="ignore", invalid="ignore"):
        r2 = np.sum((Xc[..., :2] / Xc[..., 2:]) ** 2, axis=-1)
    k1, k2 = truth.dist[:, 0, None], truth.dist[:, 1, None]
    # a point far outside the field of view can fold back into the image under strong barrel
    # distortion: keep only where the radial mapping still grows (d(r radial)/dr > 0, with margin)
    monotone = 1 + 3 * k1 * r2 + 5 * k2 * r2 * r2 > 0.2
    w, h = truth.size[:, 0, None], truth.size[:, 1, None]
    seen = (Xc[..., 2] > 0.05) & monotone & (uv[..., 0] >= 0) & (uv[..., 0] <= w - 1) \
        & (uv[..., 1] >= 0) & (uv[..., 1] <= h - 1)
    # COLMAP's adjuster refuses a point seen once, even a constant one: every solver gets the
    # corners seen by two cameras or more
    seen &= seen.sum(axis=0) >= 2
    cam, pt = np.nonzero(seen)
    rng = np.random.default_rng(seed)
    xy = uv[cam, pt] + rng.normal(0, 0.05, (len(cam), 2))
    outlier = rng.random(len(cam)) < 0.01
    angle = rng.uniform(0, 2 * np.pi, outlier.sum())
    xy[outlier] += rng.uniform(3, 8, outlier.sum())[:, None] * np.stack([np.cos(angle), np.sin(angle)], 1)
    obs = Observations(cam, np.zeros(len(cam), int), X[pt], xy, pid[pt], np.zeros(len(cam), int))
    C = len(truth)
    # fixed sizes in random directions and signs, so that every camera starts as far off
    dR = rotvec_to_matrix(np.radians(1.0) * _unit(rng.normal(size=(C, 3))))
    intr = pack_intrinsics(truth.K, truth.dist)
    intr[:, :2] *= 1 + 0.01 * _sign(rng, (C, 2))
    intr[:, 2:4] += 3.0 * _sign(rng, (C, 2))
    intr[:, 4:8] += _sign(rng, (C, 4)) * [0.02, 0.005, 3e-4, 3e-4]
    # the centre moves by 2 cm, the rotation turns about it
    centre = truth.centers + 0.02 * _unit(rng.normal(size=(C, 3)))
    R = dR @ truth.R
    start = BundleState(intr, matrix_to_rotvec(R), -np.einsum("cij,cj->ci", R, centre), np.zeros((1, 3)),
                        np.zeros((1, 3)))
    return Problem(truth, start, obs, ~outlier)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _sign(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    return rng.choice([-1.0, 1.0], size=shape)


def solve_own(p: Problem) -> tuple[BundleState, int]:
    """(state, LM iterations of both passes)."""
    C = len(p.truth)
    mask = np.zeros((C, 9), bool)
    mask[:, :N_FREE] = True
    result = bundle_adjust(p.start, p.obs, np.zeros(C, bool), np.ones(1, bool), mask, loss_scale_px=LOSS_PX)
    return result.state, result.iterations


def _unpack(x: np.ndarray, p: Problem) -> BundleState:
    v = x.reshape(-1, 6 + N_FREE)
    intr = np.concatenate([v[:, 6:], p.start.intr[:, N_FREE:]], axis=1)  # k3 as it started
    return BundleState(intr, v[:, :3], v[:, 3:6], p.start.obj_rvec, p.start.obj_t)


def solve_scipy(p: Problem) -> tuple[BundleState, int]:
    """(state, Jacobian evaluations: one per trust-region iteration)."""
    s, C, M = p.start, len(p.truth), len(p.obs)
    x0 = np.concatenate([s.cam_rvec, s.cam_t, s.intr[:, :N_FREE]], axis=1).ravel()

    def fun(x: np.ndarray) -> np.ndarray:
        # behind a camera: a large finite residual (as the project's adjuster does), never NaN
        return np.nan_to_num(residuals_of(_unpack(x, p), p.obs), nan=1e3).ravel()

    # both rows of an observation depend on its camera's 14 parameters and nothing else
    rows = np.repeat(np.arange(2 * M), 6 + N_FREE)
    cols = (np.repeat(p.obs.cam, 2)[:, None] * (6 + N_FREE) + np.arange(6 + N_FREE)).ravel()
    pattern = csr_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(2 * M, C * (6 + N_FREE)))
    res = least_squares(fun, x0, jac_sparsity=pattern, method="trf", loss="soft_l1", f_scale=LOSS_PX,
                        x_scale="jac")
    return _unpack(res.x, p), int(res.njev)


def colmap_model(p: Problem) -> tuple[pycolmap.Reconstruction, np.ndarray]:
    """The start as a COLMAP reconstruction and each observation's point2D index in its image.
    Pixels move by +0.5: COLMAP's origin is the corner of the first pixel, OpenCV's its centre (as
    formats/colmap_text.py writes them)."""
    s, obs = p.start, p.obs
    rec = pycolmap.Reconstruction()
    R = rotvec_to_matrix(s.cam_rvec)
    index = np.zeros(len(obs), int)
    for c in range(len(p.truth)):
        fx, fy, cx, cy, *dist = s.intr[c, :N_FREE]
        w, h = p.truth.size[c].astype(int)
        rec.add_camera_with_trivial_rig(pycolmap.Camera(model="OPENCV", width=int(w), height=int(h), camera_id=c + 1,
                                                        params=[fx, fy, cx + 0.5, cy + 0.5, *dist]))
        mine = np.flatnonzero(obs.cam == c)
        index[mine] = np.arange(len(mine))
        q = matrix_to_quat(R[c])
        image = pycolmap.Image(name=f"{c}.jpg", keypoints=obs.xy[mine] + 0.5, camera_id=c + 1, image_id=c + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(q[[1, 2, 3, 0]]), s.cam_t[c]))
    order = np.argsort(obs.point, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(obs.point[order]) != 0])
    for group in np.split(order, starts[1:]):
        track = pycolmap.Track()
        for m in group:
            track.add_element(int(obs.cam[m]) + 1, int(index[m]))
        rec.add_point3D(obs.local[group[0]], track)
    return rec, index


def _colmap_adjust(rec: pycolmap.Reconstruction) -> int:
    """One run of COLMAP's adjuster on rec (in place): poses and intrinsics free, points constant.
    Returns the Ceres iterations."""
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = options.refine_principal_point = options.refine_extra_params = True
    options.print_summary = False
    options.ceres.loss_function_type = pycolmap.LossFunctionType.SOFT_L1
    options.ceres.loss_function_scale = LOSS_PX
    options.ceres.solver_options.num_threads = 1
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.images:
        config.add_image(image_id)
    for point_id in rec.points3D:
        config.add_constant_point(point_id)
    summary = pycolmap.create_default_bundle_adjuster(options, config, rec).solve()
    if not summary.is_solution_usable():
        raise RuntimeError(summary.brief_report())
    # the binding gives the Ceres summary only as text
    iterations = re.search(r"Iterations: (\d+)", summary.brief_report())
    return int(iterations[1]) if iterations else 0


def _colmap_state(p: Problem, rec: pycolmap.Reconstruction) -> BundleState:
    C = len(p.truth)
    intr, rvec, t = p.start.intr.copy(), np.zeros((C, 3)), np.zeros((C, 3))
    for c in range(C):
        fx, fy, cx, cy, *dist = rec.cameras[c + 1].params
        intr[c, :N_FREE] = [fx, fy, cx - 0.5, cy - 0.5, *dist]
        pose = rec.images[c + 1].cam_from_world()
        x, y, z, w = pose.rotation.quat
        rvec[c] = matrix_to_rotvec(quat_to_matrix(np.array([w, x, y, z])))
        t[c] = pose.translation
    return BundleState(intr, rvec, t, p.start.obj_rvec, p.start.obj_t)


def solve_pycolmap(p: Problem, rec: pycolmap.Reconstruction, index: np.ndarray, outlier_pass: bool
                   ) -> tuple[BundleState, int]:
    """(state, Ceres iterations). With outlier_pass, bundle_adjust's rule after the first solve
    (drop residuals above max(4 px, 5 x median)) and a second solve, as the own solver does; COLMAP
    deletes a whole point whose track falls to one view, so a few more observations go."""
    iterations = _colmap_adjust(rec)
    if outlier_pass:
        err = np.linalg.norm(residuals_of(_colmap_state(p, rec), p.obs), axis=1)
        bad = np.flatnonzero(~(err <= max(4.0, 5 * float(np.nanmedian(err)))))
        for m in bad:
            if rec.images[int(p.obs.cam[m]) + 1].point2D(int(index[m])).has_point3D():
                rec.delete_observation(int(p.obs.cam[m]) + 1, int(index[m]))
        if len(bad):
            iterations += _colmap_adjust(rec)
    return _colmap_state(p, rec), iterations


def score(p: Problem, s: BundleState) -> dict[str, float]:
    res = residuals_of(s, p.obs)[p.inlier]
    R = rotvec_to_matrix(s.cam_rvec)
    centres = -np.einsum("cji,cj->ci", R, s.cam_t)
    centre_mm = 1000 * np.linalg.norm(centres - p.truth.centers, axis=1)
    K = pack_intrinsics(p.truth.K, p.truth.dist)
    return {"rms": float(np.sqrt(np.nanmean(np.sum(res**2, axis=1)))),
            "centre_med": float(np.median(centre_mm)), "centre_max": float(centre_mm.max()),
            "rot_max": float(rotation_angle_deg(R, p.truth.R).max()),
            "f_max": float(100 * np.abs(s.intr[:, :2] / K[:, :2] - 1).max()),
            "pp_max": float(np.linalg.norm(s.intr[:, 2:4] - K[:, 2:4], axis=1).max())}


def timed(run, repeats: int) -> tuple[float, BundleState, int]:
    best, out = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = run()
        best = min(best, time.perf_counter() - t0)
    return best, *out


def compare(cameras: int | None = None, repeats: int = 3) -> None:
    """Solve the problem with each solver and print the table and the time ratios."""
    p = make_problem(cameras)
    C, M = len(p.truth), len(p.obs)
    print(f"{C} cameras, {len(np.unique(p.obs.point))} tag corners, {M} observations "
          f"({int((~p.inlier).sum())} gross outliers), {C * (6 + N_FREE)} free parameters; "
          f"{repeats} runs each, one thread")

    rows = {"start": (float("nan"), p.start, 0)}
    rows["own"] = timed(lambda: solve_own(p), repeats)
    rows["scipy"] = timed(lambda: solve_scipy(p), repeats)
    try:
        for name, outlier_pass in (("pycolmap", False), ("pycolmap+pass", True)):
            # the Reconstruction is built anew for each run (the adjuster changes it in place) and
            # timed with it: converting the project's state is part of using COLMAP's adjuster
            best = np.inf
            for _ in range(repeats):
                t0 = time.perf_counter()
                rec, index = colmap_model(p)
                state, its = solve_pycolmap(p, rec, index, outlier_pass)
                best = min(best, time.perf_counter() - t0)
            rows[name] = (best, state, its)
    except (RuntimeError, ValueError) as exc:  # a pycolmap API or solver failure is reported, not fatal
        print(f"pycolmap: failed ({exc})")

    print()
    print("| solver | time (s) | iterations | RMS inliers (px) | centre median (mm) | centre max (mm) "
          "| rotation max (deg) | f max (%) | principal point max (px) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, (seconds, s, its) in rows.items():
        m = score(p, s)
        t = "" if np.isnan(seconds) else f"{seconds:.2f}"
        print(f"| {name} | {t} | {its or ''} | {m['rms']:.4f} | {m['centre_med']:.2f} | {m['centre_max']:.2f} | "
              f"{m['rot_max']:.4f} | {m['f_max']:.4f} | {m['pp_max']:.3f} |")
    print()
    own = rows["own"][0]
    for name in ("scipy", "pycolmap", "pycolmap+pass"):
        if name in rows:
            print(f"time {name} / own: {rows[name][0] / own:.2f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="12 cameras instead of 53")
    ap.add_argument("--repeats", type=int, default=3, help="runs per solver, the best one timed")
    args = ap.parse_args()
    compare(12 if args.quick else None, args.repeats)
    return 0


if __name__ == "__main__":
    sys.exit(main())
