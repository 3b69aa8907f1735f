"""Multi-camera calibration: manus-capture against aniposelib, side by side on the caliscope session.

    .venv/bin/python benchmarks/bench_calibration.py

The session: 4 real webcams (1280x720, 57 synchronized frames) filming an inverted 4x5 ChArUco board
with 54 mm squares (../shared/data/caliscope_4cam_charuco). Every calibration is scored the same
way, on caliscope's own 2D detections (CHARUCO/xy_CHARUCO.csv, 2175 observations of 660 board
corners): triangulate each corner from every camera that saw it, then
  - reprojection RMSE (px) of the triangulated corners,
  - metric error: neighbour corners must be 54.0 mm apart (|mean - 54| and RMS of d - 54, mm).
Rows:
  caliscope      the reference calibration shipped with the session (camera_array.toml)
  manus-capture  calibrate_rig on the four videos (detection, intrinsics, bundle adjustment)
  aniposelib     CameraGroup.calibrate_videos, the way a user runs it; aniposelib has no option for
                 a white-on-black board, so it gets videos with the grey levels inverted first
  manus-capture* calibrate_board_rig alone on manus-capture's detections (wall time of the
                 calibration step without detection)
  aniposelib*    CameraGroup.calibrate_rows fed with the same detections: the same 2D input,
                 only the calibration differs
aniposelib is not a dependency of manus-capture: `pip install --no-deps aniposelib` (its other
requirements, numba pandas jax toml, are already in the environment; its opencv-contrib-python
requirement would replace the headless OpenCV 5 build).

Then the simulated 53-camera cube (`--sim-resolution`, default 1280x720 as in MANUS-Grasps), tagged
as docs/calibration.md advises (8 x 8 tags of 9 cm a wall and the table's sides): a calibration
take is recorded (JPEG, sensor noise) and `calibrate_rig` on the take folder with nothing but the
session's tags.json (no intrinsics, no board) is timed (goal: under 3 minutes on 2 cores) and
scored against ground_truth.h5, camera by camera: fx, fy, principal point, centre, rotation and the
reprojection of points in the capture volume (the bounds of issue 19). aniposelib has no row here:
its CameraGroup calibrates from one board moved through the volume, and a take of static cameras
looking at tags on six walls gives it nothing it can use.

Last, the bundle adjustment alone: bundle_solvers.py (the project's solver, scipy's least_squares
and pycolmap on the same 53-camera tag problem), in a process of its own held to one thread.
"""

from __future__ import annotations

import csv
import dataclasses
import sys
import tempfile
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dataset_tools.calibration.board_rig import calibrate_board_rig  # noqa: E402
from dataset_tools.calibration.boards import board_from_dict  # noqa: E402
from dataset_tools.calibration.detect import detect_cameras  # noqa: E402
from dataset_tools.calibration.frames import FrameSource  # noqa: E402
from dataset_tools.calibration.report import triangulation_check  # noqa: E402
from dataset_tools.calibration.rig import calibrate_rig  # noqa: E402
from manus_core.cameras import CameraRig  # noqa: E402
from manus_core.rotations import rotation_angle_deg  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "caliscope_4cam_charuco"
VIDEOS = DATA / "calibration" / "extrinsic"
SQUARE = 0.054
BOARD = board_from_dict({"type": "charuco", "cols": 4, "rows": 5, "square": SQUARE, "marker": 0.75 * SQUARE,
                         "dictionary": "DICT_4X4_1000", "inverted": True})
IDS = ("0", "1", "2", "3")


def reference_observations() -> np.ndarray:
    with open(VIDEOS / "CHARUCO" / "xy_CHARUCO.csv") as f:
        rows = list(csv.DictReader(f))
    return np.array([[int(r["sync_index"]), int(r["cam_id"]), int(r["keypoint_id"]), float(r["img_loc_x"]),
                      float(r["img_loc_y"])] for r in rows])


def score(rig: CameraRig, obs: np.ndarray) -> dict:
    check = triangulation_check(rig, obs[:, 1].astype(int), obs[:, 0].astype(int), obs[:, 2].astype(int),
                                obs[:, 3:5], BOARD.neighbour_pairs(), SQUARE)
    # RMS of (d - 54 mm) from mean and std: sqrt(bias^2 + std^2)
    bias = check["mean_m"] - SQUARE
    return {**check, "bias_mm": abs(bias) * 1000, "dist_rms_mm": float(np.hypot(bias, check["std_m"]) * 1000)}


def caliscope_rig() -> CameraRig:
    doc = tomllib.loads((DATA / "camera_array.toml").read_text())["cameras"]
    cams = [doc[c] for c in IDS]
    return CameraRig(IDS, [c["matrix"] for c in cams], [c["distortions"] for c in cams],
                     [c["rotation"] for c in cams], [c["translation"] for c in cams], [c["size"] for c in cams])


def anipose_rig(group) -> CameraRig:
    import cv2

    cams = group.cameras
    return CameraRig(IDS, [c.get_camera_matrix() for c in cams], [np.ravel(c.get_distortions())[:5] for c in cams],
                     [cv2.Rodrigues(np.asarray(c.get_rotation(), float))[0] for c in cams],
                     [c.get_translation() for c in cams], [c.get_size() for c in cams])


def inverted_videos(folder: Path) -> list[list[str]]:
    import cv2

    out = []
    for c in IDS:
        cap = cv2.VideoCapture(str(VIDEOS / f"cam_{c}.mp4"))
        path = folder / f"cam_{c}.avi"
        writer = None
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            if writer is None:
                # MJPEG at high quality: the inversion should not add compression loss of its own
                writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 6, frame.shape[1::-1])
                writer.set(cv2.VIDEOWRITER_PROP_QUALITY, 100)
            writer.write(255 - frame)
        writer.release()
        out.append([str(path)])
    return out


def anipose_board():
    from aniposelib.boards import CharucoBoard

    return CharucoBoard(4, 5, square_length=SQUARE, marker_length=0.75 * SQUARE, marker_bits=4, dict_size=1000)


def run_anipose_videos(folder: Path):
    from aniposelib.cameras import CameraGroup

    videos = inverted_videos(folder)
    group = CameraGroup.from_names(list(IDS), fisheye=False)
    t = time.perf_counter()
    group.calibrate_videos(videos, anipose_board(), verbose=False)
    return anipose_rig(group), time.perf_counter() - t


def run_anipose_rows(detections):
    """aniposelib's calibration on manus-capture's detections (rows in aniposelib's format)."""
    from aniposelib.cameras import CameraGroup

    board = anipose_board()
    all_rows = []
    for cam in IDS:
        rows = [{"framenum": (0, f), "corners": d.xy.reshape(-1, 1, 2).astype(np.float32),
                 "ids": d.ids.reshape(-1, 1).astype(np.int32)} for f, d in sorted(detections[cam].items())]
        all_rows.append(board.fill_points_rows(rows))
    group = CameraGroup.from_names(list(IDS), fisheye=False)
    for cam in group.cameras:
        cam.set_size((1280, 720))
    t = time.perf_counter()
    group.calibrate_rows(all_rows, board, verbose=False)
    return anipose_rig(group), time.perf_counter() - t


# issue 19's bounds: focal lengths %, principal point px, centre mm, rotation deg, reprojection px
BOUNDS = {"fx %": 0.3, "fy %": 0.3, "pp px": 2.0, "centre mm": 2.0, "rot deg": 0.1, "reproj px": 0.3}


def simulated_cube(width: int, height: int, seconds: float = 0.05) -> None:
    """Record a calibration take of the 53-camera cube, calibrate it from its tags alone, score it
    against the truth."""
    from manus_core.ground_truth import GroundTruth
    from rig.layouts import make_rig
    from rig.record import record_take

    config = make_rig(resolution=(width, height), seed=1)
    # one ray per pixel: the walls are mip-mapped, so the tags come out as sharp, at a quarter of the time
    config = dataclasses.replace(config, sim=dataclasses.replace(config.sim, supersample=1, tags_per_wall=8,
                                                                 tag_size=0.09, table_tags=True))
    with tempfile.TemporaryDirectory() as tmp:
        session = Path(tmp) / "session"
        t = time.perf_counter()
        record_take(config, session, "calib", "calibration", seconds)
        recorded = time.perf_counter() - t
        t = time.perf_counter()
        result = calibrate_rig(take=session / "calib", tags=session / "tags.json", method="tags")
        wall = time.perf_counter() - t
        cams = GroundTruth.of_take(session / "calib").cameras
        truth = CameraRig(cams.ids, cams.K, cams.dist, cams.R, cams.t, [[width, height]] * len(cams.ids))
    est, ref = result.rig, truth.subset(result.rig.ids)
    X = np.random.default_rng(0).uniform(-0.3, 0.3, (2000, 3))     # the capture volume
    seen = ref.project(X)
    inside = (seen >= 0).all(-1) & (seen < ref.size[:, None]).all(-1)
    errors = {"fx %": 100 * np.abs(est.K[:, 0, 0] / ref.K[:, 0, 0] - 1),
              "fy %": 100 * np.abs(est.K[:, 1, 1] / ref.K[:, 1, 1] - 1),
              "pp px": np.abs(est.K[:, :2, 2] - ref.K[:, :2, 2]).max(axis=1),
              "centre mm": 1000 * np.linalg.norm(est.centers - ref.centers, axis=1),
              "rot deg": rotation_angle_deg(est.R, ref.R),
              "reproj px": np.nanmedian(np.where(inside, np.linalg.norm(est.project(X) - seen, axis=-1), np.nan), 1)}
    weak = sorted(c for c, e in result.extra.get("intrinsics", {}).items() if e.get("weak"))
    print(f"\nsimulated cube, {len(truth)} cameras at {width}x{height}, 8 x 8 tags of 9 cm a wall and the table's "
          f"sides, {seconds * 1000:.0f} ms calibration take (recorded in {recorded:.0f} s), intrinsics from the tags\n")
    print("| | " + " | ".join(errors) + " |")
    print("|---|" + "---|" * len(errors))
    for name, pick in (("median", np.median), ("max", np.max), ("bound", None)):
        cells = [f"{BOUNDS[k]:g}" if pick is None else f"{pick(v):.3f}" for k, v in errors.items()]
        print(f"| {name} | " + " | ".join(cells) + " |")
    worst = {k: est.ids[int(np.argmax(v))] for k, v in errors.items()}
    print("worst camera: " + ", ".join(f"{k} {c}" for k, c in worst.items()))
    over = sorted({est.ids[i] for k, v in errors.items() for i in np.flatnonzero(v > BOUNDS[k])})
    print(f"cameras outside a bound: {', '.join(over) or 'none'}; "
          f"named weakly constrained: {', '.join(weak) or 'none'}")
    print(f"manus-capture calibrate rig: {len(est)} of {len(truth)} cameras, reprojection median "
          f"{result.median_px:.3f} px, RMS {result.rms_px:.3f} px, wall time {wall:.1f} s (goal: under 180 s)")
    print("aniposelib: no result possible (it calibrates from a board moved through the volume, not wall tags)")


def solver_comparison() -> None:
    """bundle_solvers.py in a process of its own: it holds BLAS and OpenMP to one thread."""
    import subprocess

    print("\nbundle adjustment alone, 53 cameras (bundle_solvers.py)\n", flush=True)
    subprocess.run([sys.executable, str(Path(__file__).with_name("bundle_solvers.py"))], check=True)


def main() -> None:
    import argparse
    import contextlib
    import io

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sim-resolution", default="1280x720", help="WxH of the simulated cube's cameras")
    args = parser.parse_args()
    sim_size = tuple(int(x) for x in args.sim_resolution.lower().split("x"))

    obs = reference_observations()
    rows = [("caliscope (reference)", caliscope_rig(), float("nan"))]
    t = time.perf_counter()
    ours = calibrate_rig({c: VIDEOS / f"cam_{c}.mp4" for c in IDS}, board=BOARD)
    rows.append(("manus-capture", ours.rig.subset(IDS), time.perf_counter() - t))
    detections, sizes = detect_cameras({c: FrameSource((str(VIDEOS / f"cam_{c}.mp4"),)) for c in IDS}, BOARD)
    t = time.perf_counter()
    alone = calibrate_board_rig(detections, sizes, BOARD)
    rows.append(("manus-capture* (calibration)", alone.rig.subset(IDS), time.perf_counter() - t))
    quiet = io.StringIO()
    with tempfile.TemporaryDirectory() as tmp, contextlib.redirect_stdout(quiet):
        try:
            rig, seconds = run_anipose_videos(Path(tmp))
            rows.append(("aniposelib (inverted videos)", rig, seconds))
        except Exception as exc:  # report, do not hide, a failure of the other tool
            rows.append((f"aniposelib failed: {type(exc).__name__}: {exc}", None, float("nan")))
        rig, seconds = run_anipose_rows(detections)
        rows.append(("aniposelib* (our detections)", rig, seconds))
    print(f"caliscope 4-camera ChArUco session, scored on caliscope's {len(obs)} reference observations\n")
    print(f"{'calibration':32s} {'RMSE px':>8s} {'median':>7s} {'mean mm':>8s} {'|bias| mm':>9s} "
          f"{'RMS(d-54) mm':>12s} {'wall s':>7s}")
    scores = {}
    for name, rig, seconds in rows:
        if rig is None:
            print(name)
            continue
        s = score(rig, obs)
        scores[name] = (s, seconds)
        print(f"{name:32s} {s['rmse_px']:8.3f} {s['median_px']:7.3f} {s['mean_m'] * 1000:8.2f} {s['bias_mm']:9.3f} "
              f"{s['dist_rms_mm']:12.3f} {seconds:7.1f}")
    print()
    for theirs, mine in (("aniposelib (inverted videos)", "manus-capture"),
                         ("aniposelib* (our detections)", "manus-capture* (calibration)")):
        if theirs not in scores:
            continue
        (s, seconds), (m, my_seconds) = scores[theirs], scores[mine]
        print(f"{theirs} / {mine}: reprojection RMSE ratio {s['rmse_px'] / m['rmse_px']:.2f}, "
              f"metric error ratio {s['dist_rms_mm'] / m['dist_rms_mm']:.2f}, wall time ratio {seconds / my_seconds:.2f}")
    simulated_cube(*sim_size)
    solver_comparison()


if __name__ == "__main__":
    main()
