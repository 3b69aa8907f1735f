"""Triangulation against real calibrations and published numbers, outliers, and bad input."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from dataset_tools.calibration.formats import load_cameras
from dataset_tools.triangulation import triangulate, triangulate_frames
from dataset_tools.undistort import undistort_points
from manus_core.cameras import CameraRig
from manus_core.errors import TriangulationError


def _ring_rig(n: int = 8, radius: float = 2.0, k1: float = -0.25, distortion: bool = True) -> CameraRig:
    """n cameras on a ring around the origin, 1280x720, all aimed at the origin, with distortion."""
    R, t = [], []
    for a in np.linspace(0, 2 * np.pi, n, endpoint=False):
        center = np.array([radius * np.cos(a), radius * np.sin(a), 0.3 * np.sin(3 * a)])
        z = -center / np.linalg.norm(center)
        y = np.array([0.0, 0.0, -1.0]) - z * -z[2]
        y /= np.linalg.norm(y)
        rot = np.stack([np.cross(y, z), y, z])
        R.append(rot)
        t.append(-rot @ center)
    K = np.tile([[900.0, 0, 640], [0, 905, 360], [0, 0, 1]], (n, 1, 1))
    dist = np.tile([k1, 0.08, 0.001, -0.0005, -0.01], (n, 1)) * distortion
    return CameraRig(tuple(f"c{i}" for i in range(n)), K, dist, R, t, np.tile([1280, 720], (n, 1)))


def _observe(rig: CameraRig, X: np.ndarray) -> np.ndarray:
    p = rig.project(X)
    return np.concatenate([p, np.ones(p.shape[:2] + (1,))], axis=2)


# ---------------------------------------------------------------------------------------------
# real data

def _caliscope(shared_data):
    folder = shared_data / "caliscope_4cam_charuco"
    rig = load_cameras(folder / "camera_array.toml")
    with open(folder / "calibration/extrinsic/CHARUCO/xy_CHARUCO.csv") as f:
        rows = list(csv.DictReader(f))
    keys = sorted({(int(r["sync_index"]), int(r["keypoint_id"])) for r in rows})
    index = {k: i for i, k in enumerate(keys)}
    pts = np.full((len(rig), len(keys), 3), np.nan)
    for r in rows:
        pts[rig.index(r["cam_id"]), index[int(r["sync_index"]), int(r["keypoint_id"])]] = \
            [float(r["img_loc_x"]), float(r["img_loc_y"]), 1.0]
    return folder, rig, pts, index


def test_caliscope_session_reproduces_the_reference(shared_data):
    """SOURCES.md: undistort + DLT over xy_CHARUCO gives reprojection RMSE 1.6376 px, a median of
    0.87 mm from caliscope's xyz_CHARUCO and adjacent corners 53.85 mm apart (54 mm squares)."""
    folder, rig, pts, index = _caliscope(shared_data)
    X, error_px = triangulate(rig, pts, ransac=False)
    assert np.isfinite(X).all() and len(X) == 660
    residual = np.linalg.norm(rig.project(X) - pts[..., :2], axis=-1)
    seen = np.isfinite(pts[..., 0])
    assert seen.sum() == 2175
    rmse = np.sqrt(np.mean(residual[seen] ** 2))
    assert rmse == pytest.approx(1.6376, rel=0.01)
    # error_px is each point's RMS over its views: the same residuals.
    np.testing.assert_allclose(error_px, np.sqrt(np.nanmean(np.where(seen, residual, np.nan) ** 2, axis=0)))

    with open(folder / "calibration/extrinsic/CHARUCO/xyz_CHARUCO.csv") as f:
        ref = {(int(r["sync_index"]), int(r["keypoint_id"])): [float(r[c]) for c in ("x_coord", "y_coord", "z_coord")]
               for r in csv.DictReader(f)}
    d = [np.linalg.norm(X[index[k]] - v) for k, v in ref.items()]
    assert np.median(d) * 1000 == pytest.approx(0.87, rel=0.01)

    adjacent = []  # 3 x 4 inner corners, id = row * 3 + col
    for (sync, kp), i in index.items():
        row, col = divmod(kp, 3)
        for other in ([kp + 1] if col < 2 else []) + ([kp + 3] if row < 3 else []):
            if (sync, other) in index:
                adjacent.append(np.linalg.norm(X[i] - X[index[sync, other]]))
    assert np.mean(adjacent) * 1000 == pytest.approx(53.85, rel=0.01)

    # The same points as aniposelib's reference output (which works in unnormalized world
    # coordinates, so the algebraic minimum differs slightly).
    with open(folder / "expected_triangulation_aniposelib.csv") as f:
        expected = {(int(r["sync_index"]), int(r["keypoint_id"])): [float(r[c]) for c in "xyz"]
                    for r in csv.DictReader(f)}
    diff = np.array([np.linalg.norm(X[index[k]] - v) for k, v in expected.items()])
    assert np.median(diff) < 1e-5 and diff.max() < 2e-4


def _panoptic(shared_data):
    folder = shared_data / "hand_samples" / "cmu_panoptic_calibration_band1"
    rig = load_cameras(folder / "calibration_160906_band1.json")
    rig = rig.subset([i for i in rig.ids if i.startswith("00_")])  # the 31 HD cameras
    joints = []
    for frame in ("168", "169"):
        for body in json.loads((folder / f"body3DScene_00000{frame}.json").read_text())["bodies"]:
            j = np.array(body["joints19"]).reshape(19, 4)
            joints.append(j[j[:, 3] >= 0, :3] / 100)  # centimetres; confidence -1 = no joint
    X = np.concatenate(joints)
    p = rig.project(X)
    inside = ((p >= 0) & (p < rig.size[:, None, :])).all(axis=-1)
    pts = np.concatenate([p, inside[..., None].astype(float)], axis=-1)
    return rig, X, pts, inside


def test_cmu_panoptic_joints_come_back(shared_data):
    rig, X, pts, inside = _panoptic(shared_data)
    assert len(X) == 106 and inside.sum(axis=0).min() >= 10
    for ransac in (False, True):
        Y, error_px = triangulate(rig, pts, ransac=ransac)
        assert np.abs(Y - X).max() < 1e-4  # 0.1 mm
        assert error_px.max() < 1e-6


def test_cmu_panoptic_ransac_rejects_outliers(shared_data):
    rig, X, pts, inside = _panoptic(shared_data)
    rng = np.random.default_rng(0)
    cams, points = np.nonzero(inside)
    pick = rng.random(len(cams)) < 0.2
    bad = pts.copy()
    bad[cams[pick], points[pick], :2] = rng.uniform([0, 0], [1920, 1080], (pick.sum(), 2))
    plain, _ = triangulate(rig, bad, ransac=False)
    assert np.median(np.linalg.norm(plain - X, axis=1)) > 0.05  # the outliers do hurt a plain DLT
    Y, error_px, used = triangulate(rig, bad, ransac=True, return_inliers=True)
    assert np.linalg.norm(Y - X, axis=1).max() < 5e-3
    outlier = np.zeros_like(inside)
    outlier[cams[pick], points[pick]] = True
    # Every view kept is a true one; an outlier that lands within 10 px of the truth could pass,
    # none does here.
    assert not (used & outlier).any()
    assert (used == (inside & ~outlier)).mean() > 0.99


# ---------------------------------------------------------------------------------------------
# synthetic checks

def test_undistortion_inverts_the_distortion_model():
    rig = _ring_rig(2, k1=-0.3)
    rng = np.random.default_rng(0)
    xy = rng.uniform([-0.7, -0.4], [0.7, 0.4], (2, 5000, 2))
    pixels = rig.distort(xy) @ rig.K[0, :2, :2].T + rig.K[0, :2, 2]
    np.testing.assert_allclose(undistort_points(rig, pixels), xy, atol=1e-12)
    # A strong pincushion lens, every pixel of the image: the inverse series that starts the Newton
    # steps is far off in the corners here, where the distorted point is the start instead.
    lens = CameraRig(("p",), rig.K[:1], [[0.9, -1.5, 0.001, 0.0005, 2.0]], np.eye(3)[None], np.zeros((1, 3)),
                     [[1280, 720]])
    pixels = np.stack(np.meshgrid(np.arange(0, 1280, 4.0), np.arange(0, 720, 4.0)), axis=-1).reshape(1, -1, 2)
    back = undistort_points(lens, pixels)
    assert np.isfinite(back).all()
    np.testing.assert_allclose(lens.distort(back) @ lens.K[0, :2, :2].T + lens.K[0, :2, 2], pixels, atol=1e-9)
    # Far outside the image the barrel model folds over and has no inverse: NaN, not a guess.
    far = undistort_points(rig, np.array([[[40000.0, 30000.0]], [[np.nan, 1.0]]]))
    assert np.isnan(far).all()


def test_missing_views_are_never_filled_in():
    rig = _ring_rig()
    rng = np.random.default_rng(1)
    X = rng.uniform(-0.2, 0.2, (300, 3))
    pts = _observe(rig, X)
    views = rng.integers(0, 5, 300)  # 0..4 usable views per point
    for n, v in enumerate(views):
        drop = rng.permutation(len(rig))[v:]
        kind = n % 3  # three ways of saying "missing"
        if kind == 0:
            pts[drop, n, 2] = 0.0
        elif kind == 1:
            pts[drop, n, 2] = np.nan
        else:
            pts[drop, n, :2] = np.nan
    for ransac in (False, True):
        Y, error_px = triangulate(rig, pts, ransac=ransac)
        np.testing.assert_array_equal(np.isnan(Y).any(axis=1), views < 2)
        np.testing.assert_array_equal(np.isnan(error_px), views < 2)
        np.testing.assert_allclose(Y[views >= 2], X[views >= 2], atol=1e-9)
    Y, _ = triangulate(rig, pts, min_views=3)
    np.testing.assert_array_equal(np.isnan(Y).any(axis=1), views < 3)
    # All missing: every point NaN, no error.
    Y, error_px = triangulate(rig, np.full((len(rig), 7, 3), np.nan))
    assert np.isnan(Y).all() and np.isnan(error_px).all()
    # One camera, and no points at all.
    for ransac in (False, True):
        Y, error_px = triangulate(rig.subset(["c0"]), pts[:1], ransac=ransac)
        assert np.isnan(Y).all() and np.isnan(error_px).all()
    Y, error_px = triangulate(rig, pts[:, :0])
    assert Y.shape == (0, 3) and error_px.shape == (0,)


def test_a_point_behind_the_cameras_is_rejected():
    # At (2, 0, .) and (0, 2, .), looking at the origin; no distortion, whose polynomial folds over
    # far outside the image and would not keep the images of a point behind the camera.
    rig = _ring_rig(4, distortion=False).subset(["c0", "c1"])
    X = np.array([[0.0, 0.0, 0.0]])
    # A point behind both cameras still has pinhole images (x/z, y/z) that a DLT solves exactly;
    # it must not come back as a point.
    behind = np.array([[4.0, 5.0, 0.5]])
    Xc = rig.to_camera(behind)
    assert (Xc[..., 2] < 0).all()
    pix = Xc[..., :2] / Xc[..., 2:] @ rig.K[0, :2, :2].T + rig.K[0, :2, 2]
    pts = np.concatenate([pix, np.ones((2, 1, 1))], axis=2)
    for ransac in (False, True):
        Y, error_px = triangulate(rig, np.concatenate([pts, _observe(rig, X)], axis=1), ransac=ransac,
                                  threshold_px=1e6)
        assert np.isnan(Y[0]).all() and np.isnan(error_px[0])
        np.testing.assert_allclose(Y[1], X[0], atol=1e-9)


def test_confidence_weights_and_error_gate():
    rig = _ring_rig(4)
    X = np.array([[0.05, -0.02, 0.1]])
    pts = _observe(rig, X)
    pts[0, 0, 0] += 8.0  # one view off by 8 px
    biased, _ = triangulate(rig, pts, ransac=False)
    pts[0, 0, 2] = 0.05  # ... and marked as unsure
    weighted, err = triangulate(rig, pts, ransac=False)
    assert np.linalg.norm(weighted - X) < 0.2 * np.linalg.norm(biased - X)
    gated, _ = triangulate(rig, pts, ransac=False, max_error_px=err[0] / 2)
    assert np.isnan(gated).all()
    # RANSAC with a threshold below the offset drops the view and recovers the point exactly.
    clean, err_r, used = triangulate(rig, pts, ransac=True, threshold_px=4.0, return_inliers=True)
    np.testing.assert_allclose(clean, X, atol=1e-9)
    np.testing.assert_array_equal(used[:, 0], [False, True, True, True])
    assert err_r[0] < 1e-6


def test_frames_helper_and_camera_ids():
    rig = _ring_rig()
    rng = np.random.default_rng(2)
    X = rng.uniform(-0.2, 0.2, (6, 21, 3))
    kp = np.stack([_observe(rig, x) for x in X])  # (T,C,J,3)
    kp[2, :, 5, 2] = 0.0  # one joint missing in every view of frame 2
    Y, err, used = triangulate_frames(rig, kp, return_inliers=True)
    assert Y.shape == (6, 21, 3) and err.shape == (6, 21) and used.shape == (6, len(rig), 21)
    assert np.isnan(Y[2, 5]).all() and not used[2, :, 5].any()
    mask = np.ones((6, 21), dtype=bool)
    mask[2, 5] = False
    np.testing.assert_allclose(Y[mask], X[mask], atol=1e-9)
    for t in (0, 3):
        single, _ = triangulate(rig, kp[t])
        np.testing.assert_allclose(Y[t], single, atol=1e-12)
    # Rows given in another order and for a subset of the cameras, named by id.
    order = ["c5", "c1", "c3"]
    sub = kp[0][[rig.index(i) for i in order]]
    Y_sub, _ = triangulate(rig, sub, camera_ids=order)
    np.testing.assert_allclose(Y_sub, X[0], atol=1e-9)


def test_bad_input_raises_clear_errors():
    rig = _ring_rig(4)
    assert TriangulationError.exit_code == 2
    with pytest.raises(TriangulationError, match=r"has 3 cameras but the calibration has 4"):
        triangulate(rig, np.zeros((3, 5, 3)))
    with pytest.raises(TriangulationError, match=r"must be \(C, N, 3\)"):
        triangulate(rig, np.zeros((4, 5)))
    with pytest.raises(TriangulationError, match=r"cameras \['nope'\] are not in the calibration"):
        triangulate(rig, np.zeros((2, 5, 3)), camera_ids=["c0", "nope"])
    with pytest.raises(TriangulationError, match="2 camera ids for 3 cameras"):
        triangulate(rig, np.zeros((3, 5, 3)), camera_ids=["c0", "c1"])
    with pytest.raises(TriangulationError, match="must be \\(T, C, J, 3\\)"):
        triangulate_frames(rig, np.zeros((4, 5, 3)))
    with pytest.raises(TriangulationError, match="min_views"):
        triangulate(rig, np.zeros((4, 5, 3)), min_views=1)
    with pytest.raises(TriangulationError, match="not a numeric array"):
        triangulate(rig, [["a"]])
