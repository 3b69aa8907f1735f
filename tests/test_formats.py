"""Camera file formats: exact round trips, cross-checks against pycolmap and OpenCV, real files."""

from __future__ import annotations

import json
import tomllib

import cv2
import numpy as np
import pycolmap
import pytest

from dataset_tools.calibration.formats import READABLE, WRITABLE, detect_format, load_cameras, save_cameras
from manus_core.cameras import CameraRig
from manus_core.errors import CalibrationFileError


def _random_rig(n: int = 5, seed: int = 1, k3: bool = True) -> CameraRig:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    R = np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                  np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                  np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)
    K = np.zeros((n, 3, 3))
    K[:, 0, 0], K[:, 1, 1] = rng.uniform(500, 1500, n), rng.uniform(500, 1500, n)
    K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = rng.uniform(500, 700, n), rng.uniform(300, 400, n), 1
    dist = rng.normal(scale=0.05, size=(n, 5))
    if not k3:
        dist[:, 4] = 0
    # Ids like the cube's (x+00, x-00) and others that EasyMocap's keys cannot hold as they are.
    ids = ("x+00", "x-00", "cam.2", "00_03", "cam04", "c5", "c6", "c7")[:n]
    return CameraRig(ids, K, dist, R, rng.normal(size=(n, 3)),
                     np.tile([1280, 720], (n, 1)), rng.uniform(0.1, 1.0, n))


def _points_in_front(rig: CameraRig, n: int = 50, seed: int = 0) -> np.ndarray:
    """(C,n,3): for each camera, world points 1.5-3 m in front of it (random cameras share no view)."""
    rng = np.random.default_rng(seed)
    cam_pts = np.concatenate([rng.uniform(-0.3, 0.3, (n, 2)), rng.uniform(1.5, 3.0, (n, 1))], axis=1)
    return np.stack([(cam_pts - rig.t[i]) @ rig.R[i] for i in range(len(rig))])


def _assert_same(a: CameraRig, b: CameraRig, rtol: float = 0.0, atol_r: float = 0.0) -> None:
    assert a.ids == b.ids
    for name in ("K", "dist", "t", "size"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=rtol, atol=0)
    np.testing.assert_allclose(a.R, b.R, rtol=0, atol=atol_r)


@pytest.mark.parametrize("fmt,name", [("json", "cameras.json"), ("opencv-yaml", "cameras.yml"),
                                      ("easymocap", "emc"), ("colmap", "sparse"), ("manus", "optim_params.txt")])
def test_round_trip_every_writable_format(tmp_path, fmt, name):
    rig = _random_rig(k3=fmt != "manus")
    save_cameras(rig, tmp_path / name, fmt)
    assert detect_format(tmp_path / name) == fmt
    back = load_cameras(tmp_path / name)
    if fmt in ("json", "opencv-yaml", "easymocap"):
        _assert_same(rig, back)  # bit for bit: text written with round-trip precision, R stored as a matrix
    else:
        # R passes through a unit quaternion and cx, cy through COLMAP's half-pixel shift.
        _assert_same(rig, back, rtol=1e-15, atol_r=1e-15)
    if fmt in ("json", "opencv-yaml"):
        np.testing.assert_array_equal(rig.rms_px, back.rms_px)
    for i, X in enumerate(_points_in_front(rig)):
        np.testing.assert_allclose(back.project(X)[i], rig.project(X)[i], rtol=0, atol=1e-9)


def test_formats_refuse_what_they_cannot_hold(tmp_path):
    rig = _random_rig(k3=True)
    with pytest.raises(CalibrationFileError, match="k3"):
        save_cameras(rig, tmp_path / "p.txt", "manus")
    save_cameras(rig, tmp_path / "p.txt", "manus", lossy=True)
    np.testing.assert_array_equal(load_cameras(tmp_path / "p.txt").dist[:, 4], 0)
    K = rig.K.copy()
    K[:, 0, 1] = 0.5
    skewed = CameraRig(rig.ids, K, rig.dist, rig.R, rig.t, rig.size)
    with pytest.raises(CalibrationFileError, match="skew"):
        save_cameras(skewed, tmp_path / "colmap", "colmap")
    with pytest.raises(CalibrationFileError, match="cannot write format"):
        save_cameras(rig, tmp_path / "x", "anipose")
    spaced = CameraRig(("cam 0",) + rig.ids[1:], rig.K, rig.dist, rig.R, rig.t, rig.size)
    with pytest.raises(CalibrationFileError, match="whitespace"):
        save_cameras(spaced, tmp_path / "colmap", "colmap")


def test_colmap_export_projects_like_pycolmap(tmp_path):
    """pycolmap reads the exported model and projects every point where we do, 0.5 px apart
    (COLMAP's pixel origin is the corner of the first pixel, OpenCV's its centre)."""
    rig = _random_rig()
    save_cameras(rig, tmp_path, "colmap")
    rec = pycolmap.Reconstruction(str(tmp_path))
    points = _points_in_front(rig)
    for image in rec.images.values():
        i = rig.ids.index(image.name.removesuffix(".jpg"))
        cam_from_world = image.cam_from_world().matrix()
        np.testing.assert_allclose(cam_from_world[:, :3], rig.R[i], atol=1e-15)
        Xc = points[i] @ cam_from_world[:, :3].T + cam_from_world[:, 3]
        ours = rig.project(points[i])[i]
        np.testing.assert_allclose(rec.cameras[image.camera_id].img_from_cam(Xc) - 0.5, ours, atol=1e-8)


def _pycolmap_rig_model(folder, frames: int):
    """A two-camera rig written by pycolmap 4 (rigs.txt, frames.txt), moving between frames."""
    rec = pycolmap.Reconstruction()
    for cid in (1, 2):
        rec.add_camera(pycolmap.Camera(model="OPENCV", width=640, height=480, camera_id=cid,
                                       params=[500.0 + cid, 501, 320, 240, 0.1, -0.01, 0.001, 0.002]))
    rig = pycolmap.Rig(rig_id=1)
    rig.add_ref_sensor(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, 1))
    q = np.array([0.1, 0.2, 0.3, 0.9]) / np.linalg.norm([0.1, 0.2, 0.3, 0.9])  # x, y, z, w
    sensor_from_rig = pycolmap.Rigid3d(pycolmap.Rotation3d(q), np.array([0.5, 0.0, 0.1]))
    rig.add_sensor(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, 2), sensor_from_rig)
    rec.add_rig(rig)
    image_id = 1
    for fid in range(1, frames + 1):
        frame = pycolmap.Frame(frame_id=fid, rig_id=1)
        turn = pycolmap.Rotation3d(np.array([0, 0, np.sin(0.1 * fid), np.cos(0.1 * fid)]))
        frame.rig_from_world = pycolmap.Rigid3d(turn, np.array([0.1 * fid, 0.2, 3.0]))
        for cid in (1, 2):
            frame.add_data_id(pycolmap.data_t(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, cid), image_id + cid - 1))
        rec.add_frame(frame)
        for cid in (1, 2):
            rec.add_image(pycolmap.Image(name=f"cam{cid}/{fid:04d}.jpg", camera_id=cid, image_id=image_id,
                                         frame_id=fid))
            image_id += 1
        rec.register_frame(fid)
    folder.mkdir()
    rec.write_text(str(folder))
    return rec, sensor_from_rig


def test_colmap_rigs_and_frames(tmp_path):
    # One frame: the cameras' world poses, named after their image folders.
    rec, _ = _pycolmap_rig_model(tmp_path / "one", frames=1)
    rig = load_cameras(tmp_path / "one")
    assert rig.ids == ("cam1", "cam2")
    for image in rec.images.values():
        i = rig.ids.index(image.name.split("/")[0])
        np.testing.assert_allclose(np.c_[rig.R[i], rig.t[i]], image.cam_from_world().matrix(), atol=1e-12)
    np.testing.assert_allclose(rig.K[0], [[501, 0, 319.5], [0, 501, 239.5], [0, 0, 1]])
    # A moving rig: the fixed calibration is each camera's pose in the rig.
    _, sensor_from_rig = _pycolmap_rig_model(tmp_path / "moving", frames=3)
    rig = load_cameras(tmp_path / "moving")
    np.testing.assert_allclose(np.c_[rig.R[0], rig.t[0]], np.eye(3, 4), atol=1e-15)
    np.testing.assert_allclose(np.c_[rig.R[1], rig.t[1]], sensor_from_rig.matrix(), atol=1e-12)
    # images.txt edited behind frames.txt's back is caught.
    images = tmp_path / "one" / "images.txt"
    lines = images.read_text().splitlines()
    i = next(k for k, line in enumerate(lines) if line and not line.startswith("#"))
    fields = lines[i].split()
    fields[5] = str(float(fields[5]) + 0.01)
    lines[i] = " ".join(fields)
    images.write_text("\n".join(lines) + "\n")
    with pytest.raises(CalibrationFileError, match="disagrees with rigs.txt and frames.txt"):
        load_cameras(tmp_path / "one")


def _cv2_project(X, R, t, K, dist):
    rvec = cv2.Rodrigues(np.asarray(R, dtype=np.float64))[0] if np.size(R) == 9 else np.asarray(R, dtype=np.float64)
    tvec = np.asarray(t, dtype=np.float64).reshape(3, 1)
    return cv2.projectPoints(np.ascontiguousarray(X, dtype=np.float64), rvec, tvec, np.asarray(K, dtype=np.float64),
                             np.asarray(dist, dtype=np.float64))[0].reshape(-1, 2)


@pytest.mark.parametrize("session", ["7cam-allen-mouse", "12cam-allen-mouse"])
def test_anipose_calibrations_project_like_opencv(shared_data, session):
    path = shared_data / "aniposelib_calibrations" / session / "calibration.toml"
    raw = tomllib.loads(path.read_text())
    cams = [raw[k] for k in raw if k.startswith("cam_")]
    rig = load_cameras(path, units="mm")  # anipose keeps the board's unit: millimetres here
    assert detect_format(path) == "anipose" and rig.ids == tuple(c["name"] for c in cams)
    for i, cam in enumerate(cams):
        # Points 0.5-1.5 m in front of the camera, in the file's millimetres.
        R = cv2.Rodrigues(np.array(cam["rotation"]))[0]
        rng = np.random.default_rng(i)
        in_cam = np.c_[rng.uniform(-100, 100, (20, 2)), rng.uniform(500, 1500, 20)]
        X_mm = (in_cam - cam["translation"]) @ R
        expected = _cv2_project(X_mm, cam["rotation"], cam["translation"], cam["matrix"], cam["distortions"])
        np.testing.assert_allclose(rig.project(X_mm / 1000)[i], expected, atol=1e-6)
        assert tuple(rig.size[i]) == tuple(cam["size"])


def test_caliscope_camera_array_and_config_agree(shared_data):
    folder = shared_data / "caliscope_4cam_charuco"
    rig = load_cameras(folder / "camera_array.toml")
    old = load_cameras(folder / "config.toml")
    _assert_same(rig, old)
    assert detect_format(folder / "camera_array.toml") == "caliscope"
    raw = tomllib.loads((folder / "camera_array.toml").read_text())["cameras"]
    np.testing.assert_array_equal(rig.rms_px, [raw[k]["error"] for k in sorted(raw, key=int)])  # 0.541 ... 0.329
    X = np.random.default_rng(0).uniform(-0.2, 0.2, (30, 3)) + [0.0, 0.2, 0.5]  # the board's region
    for i, key in enumerate(sorted(raw, key=int)):
        cam = raw[key]
        expected = _cv2_project(X, cam["rotation"], cam["translation"], cam["matrix"], cam["distortions"])
        np.testing.assert_allclose(rig.project(X)[i], expected, atol=1e-6)


def test_cmu_panoptic_calibration(shared_data):
    folder = shared_data / "hand_samples" / "cmu_panoptic_calibration_band1"
    path = folder / "calibration_160906_band1.json"
    raw = json.loads(path.read_text())["cameras"]
    rig = load_cameras(path)
    assert detect_format(path) == "panoptic" and len(rig) == 520
    body = np.array(json.loads((folder / "body3DScene_00000168.json").read_text())["bodies"][0]["joints19"])
    X_cm = body.reshape(19, 4)[:, :3]
    proj = rig.project(X_cm / 100)  # the file is in centimetres, the rig in metres
    for i, cam in enumerate(raw):
        expected = _cv2_project(X_cm, cam["R"], cam["t"], cam["K"], cam["distCoef"])
        front = np.isfinite(proj[i, :, 0])  # OpenCV also projects points behind the camera
        assert front.sum() >= 10
        np.testing.assert_allclose(proj[i, front], expected[front], atol=1e-6)
    hd = [i for i, cam in enumerate(raw) if cam["type"] == "hd"]
    assert len(hd) == 31
    p = proj[hd]
    inside = ((p >= 0) & (p < rig.size[hd][:, None, :])).all(axis=-1).all(axis=1)
    assert inside.sum() == 9  # SOURCES.md: 9 of 31 HD cameras see all 19 joints of body 0 in frame 168


EASYMOCAP_INTRI = """%YAML:1.0
---
names:
   - "01"
   - "02"
K_01: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 1000., 0., 640., 0., 1001., 360., 0., 0., 1. ]
dist_01: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [ -0.1, 0.01, 0., 0., 0. ]
K_02: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 900., 0., 630., 0., 900., 350., 0., 0., 1. ]
dist_02: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [ 0., 0., 0., 0., 0. ]
"""
EASYMOCAP_EXTRI = """%YAML:1.0
---
names:
   - "01"
   - "02"
R_01: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [ 0., 0., 0. ]
T_01: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [ 0., 0., 2. ]
R_02: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [ 0., 1.5707963267948966, 0. ]
T_02: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [ 0.1, 0., 2. ]
"""


def test_easymocap_as_easymocap_writes_it(tmp_path):
    """Rodrigues-only extri.yml (no Rot_), names that look numeric, no image size."""
    (tmp_path / "intri.yml").write_text(EASYMOCAP_INTRI)
    (tmp_path / "extri.yml").write_text(EASYMOCAP_EXTRI)
    rig = load_cameras(tmp_path / "intri.yml")
    assert rig.ids == ("01", "02")
    np.testing.assert_allclose(rig.R[1], [[0, 0, 1], [0, 1, 0], [-1, 0, 0]], atol=1e-15)
    np.testing.assert_array_equal(rig.t[1], [0.1, 0, 2])
    np.testing.assert_array_equal(rig.dist[0], [-0.1, 0.01, 0, 0, 0])
    np.testing.assert_array_equal(rig.size, 0)  # unknown, not guessed


def test_opencv_single_camera_file(tmp_path):
    fs = cv2.FileStorage(str(tmp_path / "out_camera_data.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", np.array([[535.9, 0, 342.3], [0, 535.9, 235.6], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.array([[-0.27, 0.06, 0.001, -0.0003, 0.1]]))
    fs.write("avg_reprojection_error", 0.39)
    fs.release()
    rig = load_cameras(tmp_path / "out_camera_data.yml")
    assert rig.ids == ("out_camera_data",) and rig.rms_px[0] == 0.39
    np.testing.assert_array_equal(rig.size[0], [640, 480])
    np.testing.assert_array_equal(rig.R[0], np.eye(3))


def test_bad_files_name_the_file_and_the_problem(tmp_path):
    assert CalibrationFileError.exit_code == 2
    with pytest.raises(CalibrationFileError, match="no such calibration"):
        load_cameras(tmp_path / "missing.json")
    with pytest.raises(CalibrationFileError, match="without a calibration"):
        load_cameras(tmp_path)
    bad = tmp_path / "optim_params.txt"
    bad.write_text("# header\n0 1280 720 1000 1000 640 360 0 0 0 0 cam0 1 0 0 0 0 0\n")
    with pytest.raises(CalibrationFileError, match=r"optim_params.txt:2: 18 fields, expected 19"):
        load_cameras(bad)
    folder = tmp_path / "colmap"
    folder.mkdir()
    (folder / "cameras.txt").write_text("1 OPENCV_FISHEYE 640 480 500 500 320 240 0 0 0 0\n")
    (folder / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.jpg\n\n")
    with pytest.raises(CalibrationFileError, match=r"cameras.txt:1: camera model 'OPENCV_FISHEYE' is not supported"):
        load_cameras(folder)
    doc = _random_rig(2).to_json()
    doc["cameras"][1]["R"] = [[1, 0, 0], [0, 1, 0], [0, 0, 2]]
    (tmp_path / "c.json").write_text(json.dumps(doc))
    with pytest.raises(CalibrationFileError, match="'x-00' has a rotation that is not a rotation"):
        load_cameras(tmp_path / "c.json")
    (tmp_path / "c.json").write_text("{")
    with pytest.raises(CalibrationFileError, match="c.json: not JSON"):
        load_cameras(tmp_path / "c.json")
    toml = tmp_path / "calibration.toml"
    toml.write_text('[cam_0]\nname = "a"\nsize = [640, 480]\nmatrix = [[500, 0, 320], [0, 500, 240], [0, 0, 1]]\n'
                    'distortions = [0, 0, 0, 0, 0]\n')
    with pytest.raises(CalibrationFileError, match="camera 'a' has no rotation, translation"):
        load_cameras(toml)
    with pytest.raises(CalibrationFileError, match="unknown length unit"):
        load_cameras(toml, units="inch")
    assert set(WRITABLE) < set(READABLE)
