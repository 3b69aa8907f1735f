"""DATASET.h5 (round trip, resume, atomic output), bone lengths and the subject file, the simulated detector."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from dataset_tools.hand.bones import BONE_NAMES, estimate_bone_lengths, load_subject, save_subject
from dataset_tools.simulated_detector import SimulatedDetector, joints_at, keypoints_for_take, true_rig
from manus_core.dataset import FLAGS, DatasetWriter, TakeAnnotation, add_arrays, read_dataset
from manus_core.errors import BoneLengthError, DatasetError, GroundTruthError, SimulatedDetectorError
from manus_core.ground_truth import (
    LABEL_FRAMES,
    LABEL_IMAGE,
    LABEL_OBJECT,
    GroundTruth,
    TruthCameras,
    TruthFrames,
    TruthHand,
    write_record,
)
from manus_core.skeleton import BONES, DEFAULT_BONE_LENGTHS, LOWER, UPPER, HandSkeleton
from rig.layouts import make_rig
from rig.sim.cube import true_cameras


def make_annotation(key: str, n_t: int = 30, n_c: int = 4, seed: int = 0) -> TakeAnnotation:
    rng = np.random.default_rng(seed)
    frame_index = np.tile(np.arange(n_t)[:, None], (1, n_c))
    frame_index[3, 1] = -1
    kp = rng.uniform(0, 1000, (n_t, n_c, 21, 3)).astype(np.float32)
    kp[3, 1] = (np.nan, np.nan, 0)
    x3 = rng.normal(size=(n_t, 21, 3))
    x3[5, 7] = np.nan
    return TakeAnnotation(key, tuple(f"cam{i}" for i in range(n_c)), 10**9 + np.arange(n_t) * 8_333_333,
                          frame_index, kp, x3, rng.uniform(0, 3, (n_t, 21)), rng.integers(0, n_c, (n_t, 21)),
                          rng.normal(size=(n_t, 26)), rng.normal(size=(n_t, 26)), DEFAULT_BONE_LENGTHS.copy(),
                          rng.uniform(0, 1e-3, n_t), rng.integers(0, 16, n_t).astype(np.uint8),
                          {"kind": "grasp", "skeleton": {"name": "test"}, "calibration": "CALIB",
                           "calibration_sha256": "ab" * 32, "bone_source": "given"})


def assert_same(a: TakeAnnotation, b: TakeAnnotation) -> None:
    assert a.key == b.key and a.cameras == b.cameras
    for name in ("frame_ns", "frame_index", "keypoints2d", "keypoints3d", "keypoints3d_error_px", "keypoints3d_views",
                 "joint_angles_raw", "joint_angles", "bone_lengths", "ik_residual_m", "flags"):
        x, y = getattr(a, name), getattr(b, name)
        np.testing.assert_allclose(np.asarray(x, np.float64), np.asarray(y, np.float64), rtol=1e-6, atol=1e-6,
                                   err_msg=name)


def test_round_trip_keeps_arrays_attributes_and_layout(tmp_path):
    out = tmp_path / "DATASET.h5"
    a, b = make_annotation("S1/grasp_01"), make_annotation("S2/grasp_01", n_t=7, n_c=2, seed=1)
    with DatasetWriter(out) as w:
        w.add(a)
        w.add(b)
    ds = read_dataset(out)
    assert ds.takes == ["S1/grasp_01", "S2/grasp_01"] and len(ds) == 2
    back = ds["S1/grasp_01"]
    assert_same(a, back)
    assert back.attrs["skeleton"] == {"name": "test"} and back.attrs["flags"] == FLAGS
    assert back.attrs["calibration_sha256"] == "ab" * 32 and back.attrs["bone_source"] == "given"
    assert_same(b, ds["S2/grasp_01"])
    assert np.isnan(back.keypoints3d[5, 7]).all() and back.frame_index[3, 1] == -1
    with h5py.File(out, "r") as f:
        assert f.attrs["format"] == "manus-capture dataset" and f.attrs["version"] == 1
        assert str(f.attrs["software"]).startswith("manus-capture")
        kp = f["S1/grasp_01/keypoints2d"]
        assert kp.compression == "gzip" and kp.chunks is not None and kp.dtype == np.float32
    assert not (tmp_path / ".DATASET.h5.parts").exists()
    with pytest.raises(KeyError, match="no take"):
        ds["S3/nothing"]


def test_interrupted_writer_resumes_and_an_existing_output_grows(tmp_path):
    out = tmp_path / "DATASET.h5"
    first = make_annotation("S1/hand_01", seed=2)
    with pytest.raises(RuntimeError):
        with DatasetWriter(out) as w:
            w.add(first)
            raise RuntimeError("killed while working on the next take")
    assert not out.exists()                       # nothing under the final name
    w = DatasetWriter(out)
    assert w.done == {"S1/hand_01"}               # but the finished take is kept for the next run
    second = make_annotation("S1/grasp_01", seed=3)
    w.add(second)
    assert w.finalize() == ["S1/grasp_01", "S1/hand_01"]
    # A later run adds a take and keeps the others.
    w = DatasetWriter(out)
    assert w.done == {"S1/hand_01", "S1/grasp_01"}
    w.add(make_annotation("S1/grasp_02", seed=4))
    w.finalize()
    ds = read_dataset(out)
    assert ds.takes == ["S1/grasp_01", "S1/grasp_02", "S1/hand_01"]
    assert_same(first, ds["S1/hand_01"])
    # force drops an interrupted run's parts, never the output's other takes.
    DatasetWriter(out).add(make_annotation("S1/grasp_01", seed=6))
    w = DatasetWriter(out, force=True)
    assert w.saved == [] and w.done == {"S1/hand_01", "S1/grasp_01", "S1/grasp_02"}
    replaced = make_annotation("S1/grasp_01", seed=5)
    w.add(replaced)
    w.finalize()
    ds = read_dataset(out)
    assert ds.takes == ["S1/grasp_01", "S1/grasp_02", "S1/hand_01"]
    assert_same(replaced, ds["S1/grasp_01"])


def test_a_stage_part_is_replaced_whole_and_a_take_named_like_a_stage_is_still_a_take(tmp_path):
    path = tmp_path / "DATASET.h5"
    with DatasetWriter(path) as w:
        w.add(make_annotation("S/grasp"))
    masks = np.zeros((2, 4, 3, 3), bool)
    add_arrays(path, "S/grasp", {"masks/hand": masks, "paint/masks": masks}, stage="segment")
    add_arrays(path, "S/grasp", {"masks/hand": masks}, stage="segment")   # redone without a swatch
    with h5py.File(path, "r") as f:
        assert "paint" not in f["S/grasp"] and "joint_angles" in f["S/grasp"]
    add_arrays(path, "S/masks", {"masks/hand": masks}, stage="segment")   # a take folder called "masks"
    ds = read_dataset(path)
    assert ds.takes == ["S/grasp", "S/masks"] and ds.stages("S/masks") == {"segment"}
    assert ds.annotated == ["S/grasp"]


def test_not_a_dataset_and_bad_shapes_are_clear_errors(tmp_path):
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["x"] = 1
    with pytest.raises(DatasetError, match="not a manus-capture dataset"):
        read_dataset(other)
    with pytest.raises(DatasetError, match="no such dataset"):
        read_dataset(tmp_path / "missing.h5")
    (tmp_path / "text.h5").write_text("hello")
    with pytest.raises(DatasetError, match="cannot be read as HDF5"):
        read_dataset(tmp_path / "text.h5")
    a = make_annotation("S/t")
    with pytest.raises(DatasetError, match="joint_angles has shape"):
        TakeAnnotation(a.key, a.cameras, a.frame_ns, a.frame_index, a.keypoints2d, a.keypoints3d,
                       a.keypoints3d_error_px, a.keypoints3d_views, a.joint_angles_raw, a.joint_angles[:, :20],
                       a.bone_lengths, a.ik_residual_m, a.flags)


def noisy_hand_joints(n: int, bones: np.ndarray, noise_m: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    a = np.zeros((n, 26))
    a[:, :3] = rng.normal(size=(n, 3))
    a[:, 6:] = rng.uniform(LOWER[6:], UPPER[6:], (n, 20))
    X = HandSkeleton(bones).forward(a) + rng.normal(scale=noise_m, size=(n, 21, 3))
    err = np.full((n, 21), 1.0)
    return X, err


def test_bone_lengths_are_robust_to_outliers_and_high_error_frames(tmp_path):
    bones = DEFAULT_BONE_LENGTHS * 1.08
    X, err = noisy_hand_joints(300, bones, 0.5e-3, seed=0)
    rng = np.random.default_rng(1)
    bad = rng.random((300, 21)) < 0.1
    X[bad] += rng.normal(scale=0.03, size=(int(bad.sum()), 3))      # 10% wild joints, errors look fine
    err[:40] = 25.0                                                   # 40 frames flagged by triangulation
    X[:40] += rng.normal(scale=0.02, size=(40, 21, 3))
    X[rng.random((300, 21)) < 0.05] = np.nan
    est = estimate_bone_lengths(X, err)
    assert np.abs(est.bone_lengths - bones).max() < 0.5e-3
    assert est.max_error_px == 2.0 and est.samples.min() < 260 and est.estimated == ()
    median = estimate_bone_lengths(X, err, method="median")
    assert np.abs(median.bone_lengths - bones).max() < 0.5e-3
    plain_mean = np.nanmean(np.linalg.norm(X[:, BONES[:, 1]] - X[:, BONES[:, 0]], axis=-1), axis=0)
    assert np.abs(plain_mean - bones).max() > 3e-3       # what a plain mean would have given
    # Several takes at once, and a skeleton with those bones.
    X2, err2 = noisy_hand_joints(100, bones, 0.5e-3, seed=2)
    both = estimate_bone_lengths([X[40:], X2], [err[40:], err2])
    assert np.abs(both.bone_lengths - bones).max() < 0.5e-3
    np.testing.assert_allclose(both.skeleton().bone_lengths, both.bone_lengths)


def test_unmeasured_bones_come_from_the_rescaled_default_and_the_subject_file_round_trips(tmp_path):
    bones = DEFAULT_BONE_LENGTHS * 0.9
    X, err = noisy_hand_joints(50, bones, 0.2e-3, seed=3)
    X[:, 20] = np.nan                                   # pinky tip never seen: bone 19 unmeasured
    est = estimate_bone_lengths(X, err)
    assert est.estimated == (BONE_NAMES[19],) and BONE_NAMES[19] == "pinky_dip-pinky_tip"
    assert est.scale == pytest.approx(0.9, abs=0.005)
    assert est.bone_lengths[19] == pytest.approx(0.9 * DEFAULT_BONE_LENGTHS[19], abs=0.2e-3)
    path = save_subject(tmp_path / "S1" / "subjects" / "s01.json", "s01", est, ["hand_01"], "manus-capture test")
    doc = json.loads(path.read_text())
    assert doc["subject"] == "s01" and doc["units"] == "m" and len(doc["bone_lengths"]) == 20
    assert doc["takes"] == ["hand_01"] and doc["spread_m"][19] is None
    back = load_subject(path)
    np.testing.assert_allclose(back.bone_lengths, est.bone_lengths)
    assert back.estimated == est.estimated
    with pytest.raises(BoneLengthError, match="no bone has 10 good samples"):
        estimate_bone_lengths(np.full((30, 21, 3), np.nan))
    path.write_text(json.dumps({**doc, "bone_lengths": [0.01] * 19}))
    with pytest.raises(BoneLengthError, match="20 positive"):
        load_subject(path)
    with pytest.raises(BoneLengthError, match="no such subject file"):
        load_subject(tmp_path / "none.json")


@pytest.fixture(scope="module")
def cube12():
    return true_cameras(make_rig("cube53", cameras=12, resolution=(640, 360)))


def test_simulated_detector_noise_outliers_and_dropouts(cube12):
    rng = np.random.default_rng(0)
    a = np.zeros((40, 26))
    a[:, 3:6] = rng.uniform(-0.05, 0.05, (40, 3))
    a[:, 6:] = rng.uniform(0, 0.3, (40, 20))
    X = HandSkeleton().forward(a)
    exact = SimulatedDetector(noise_px=0, outlier_rate=0, self_occlusion=False).detect(cube12, X)
    truth = cube12.project(X.reshape(-1, 3)).reshape(12, 40, 21, 2).transpose(1, 0, 2, 3)
    seen = exact[..., 2] > 0
    np.testing.assert_allclose(exact[seen][:, :2], truth[seen], atol=1e-9)
    kp = SimulatedDetector(noise_px=2.0, outlier_rate=0.1, dropout_rate=0.2, self_occlusion=False,
                           seed=1).detect(cube12, X)
    visible = kp[..., 2] > 0
    assert 0.75 < visible[seen].mean() < 0.85                       # 20% dropped at random
    assert not visible[~seen].any()                                  # never invented where unseen
    assert np.isnan(kp[~visible][:, :2]).all() and (kp[~visible][:, 2] == 0).all()
    d = kp[visible][:, :2] - truth[visible]
    far = np.hypot(*d.T) > 15
    assert 0.08 < far.mean() < 0.12                                   # 10% outliers
    assert np.std(d[~far]) == pytest.approx(2.0, rel=0.05)            # 2 px per axis
    c = kp[visible][:, 2]
    assert c.min() >= 0.8 and c.max() <= 1.0


def test_simulated_detector_occlusion_models(cube12):
    # A flat open hand (palm facing -z) hides none of its joints from cameras above or below it.
    X = HandSkeleton().forward(np.zeros((1, 26)))
    det = SimulatedDetector(noise_px=0, outlier_rate=0, confidence=(1, 1))
    centers = cube12.centers
    steep = np.abs(centers[:, 2] - X[0, 0, 2]) / np.linalg.norm(centers - X[0, 0], axis=1) > 0.7
    assert steep.sum() >= 2
    assert (det.detect(cube12, X)[0, steep, :, 2] > 0).all()
    # A fist in front of a camera hides the fingertips behind the knuckles for a camera behind the hand.
    fist = np.zeros((1, 26))
    fist[0, 6 + 4 + np.array([0, 2, 3])] = 1.5
    fist[0, 6 + 8 + np.array([0, 2, 3])] = 1.5
    Xf = HandSkeleton().forward(fist)
    hidden = det.detect(cube12, Xf)[0, :, 8, 2] == 0           # index tip
    toward_palm = (centers - Xf[0, 0]) @ np.array([0, 0, -1.0]) > 0.3
    assert hidden[~toward_palm].any() and not hidden.all()
    # An occluder (a wall at x = 0.05 for every ray) hides the joints beyond it.
    def wall(frames, origins, dirs):
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (0.05 - origins[:, 0]) / dirs[:, 0]
        return np.where(s > 0, s, np.inf)
    walled = SimulatedDetector(noise_px=0, outlier_rate=0, self_occlusion=False).detect(cube12, X, occluder=wall)
    side = np.sign(centers[:, 0] - 0.05)
    beyond = (np.sign(X[0, :, 0] - 0.05)[None, :] != side[:, None])
    assert not (walled[0, ..., 2] > 0)[beyond].any()
    # Labels: a joint on an object pixel is hidden.
    labels = np.zeros((12, 360, 640), np.uint8)
    labels[:, :, :320] = 2
    lab = SimulatedDetector(noise_px=0, outlier_rate=0, self_occlusion=False).detect(cube12, X, labels={0: labels})
    u = lab[0, ..., 0]
    assert np.nanmin(u) >= 319.5
    with pytest.raises(SimulatedDetectorError, match="joints3d"):
        det.detect(cube12, np.zeros((3, 20, 3)))
    with pytest.raises(SimulatedDetectorError, match="outlier_rate"):
        SimulatedDetector(outlier_rate=1.5)


def test_joints_are_interpolated_to_exposure_times():
    ticks = 10**9 + np.arange(5) * 10_000_000
    joints = np.arange(5, dtype=np.float64)[:, None, None] * np.ones((5, 21, 3))
    t = np.array([[ticks[1] + 2_500_000, np.nan], [ticks[3], ticks[4] + 10**7]])
    out = joints_at(ticks, joints, t)
    assert out[0, 0, 0, 0] == pytest.approx(1.25) and np.isnan(out[0, 1]).all()
    assert out[1, 0, 0, 0] == 3.0 and out[1, 1, 0, 0] == 4.0


def test_keypoints_of_a_simulated_take_follow_exposures_drops_and_labels(cube12, tmp_path):
    """Each camera sees the hand at its own exposure; a dropped frame is missing; the ground
    truth's label images hide joints on object pixels, only in the frame they were rendered for."""
    n_t, n_c = 10, len(cube12)
    rng = np.random.default_rng(0)
    ticks = 10**9 + np.arange(n_t) * 10_000_000
    exposure = ticks[None] + rng.integers(0, 6_000_000, n_c)[:, None]
    dropped = np.zeros((n_c, n_t), bool)
    dropped[1, 3] = True
    angles = np.zeros((n_t, 26))
    angles[:, 3] = np.arange(n_t) * 1e-3                   # the wrist moves 1 mm along x per tick
    skeleton = HandSkeleton()
    joints = skeleton.forward(angles)
    labels = np.zeros((n_c, 1, 360, 640), np.uint8)
    labels[0] = LABEL_OBJECT                                  # camera 0, tick 4: the object fills the view
    path = tmp_path / "ground_truth.h5"
    with h5py.File(path, "w") as f:
        write_record(f, TruthCameras(cube12.ids, cube12.K, cube12.dist, cube12.R, cube12.t, cube12.size))
        write_record(f, TruthFrames(ticks, exposure, dropped))
        f[LABEL_FRAMES], f[LABEL_IMAGE] = np.array([4]), labels
    gt = GroundTruth(path)
    with pytest.raises(GroundTruthError, match="no hand group"):
        gt.hand
    with h5py.File(path, "a") as f:
        write_record(f, TruthHand(angles, joints, skeleton.bone_lengths))
    gt = GroundTruth(path)
    assert gt.cameras.ids == cube12.ids and gt.label_frames.tolist() == [4]
    host = (exposure.T + 2_500_000).astype(np.float64)     # arrivals 2.5 ms after the exposures
    host[3, 1] = np.nan                                    # the dropped frame never arrived
    kp = keypoints_for_take(gt, true_rig(gt, cube12.ids), host,
                            SimulatedDetector(noise_px=0, outlier_rate=0, self_occlusion=False))
    assert (kp[4, 0, :, 2] == 0).all() and (kp[4, 1:, :, 2] > 0).all() and (kp[5, 0, :, 2] > 0).all()
    assert (kp[3, 1, :, 2] == 0).all() and np.isnan(kp[3, 1, :, :2]).all()
    at_exposure = joints_at(ticks, joints, exposure.T.astype(np.float64))   # (T,C,21,3)
    r, c = 7, 5
    np.testing.assert_allclose(kp[r, c, :, :2], cube12.subset([cube12.ids[c]]).project(at_exposure[r, c])[0],
                               atol=1e-6)
    shift = (exposure[c, r] - ticks[r]) / 10_000_000 * 1e-3
    np.testing.assert_allclose(at_exposure[r, c] - joints[r], np.broadcast_to([shift, 0, 0], (21, 3)), atol=1e-12)


def test_ground_truth_errors_name_the_file_and_the_key(tmp_path):
    with pytest.raises(GroundTruthError, match=r"ground_truth.h5: missing \(only simulated takes"):
        GroundTruth.of_take(tmp_path)
    path = tmp_path / "ground_truth.h5"
    path.write_text("not HDF5")
    with pytest.raises(GroundTruthError, match="ground_truth.h5: cannot be read as HDF5"):
        GroundTruth(path).frames
    with h5py.File(path, "w") as f:
        f["frames/tick_ns"] = np.arange(3)
    gt = GroundTruth(path)
    with pytest.raises(GroundTruthError, match="ground_truth.h5: missing frames/exposure_mid_ns"):
        gt.frames
    with pytest.raises(GroundTruthError, match="ground_truth.h5: missing labels/image"):
        gt.labels()
    assert gt.label_frames.size == 0 and gt.has(TruthFrames) and not gt.has(TruthHand)
