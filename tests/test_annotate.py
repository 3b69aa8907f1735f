"""The annotate stage: accuracy on the simulated 53-camera cube, takes on disk, pool/Dask, resume, bad input."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

import dataset_tools.annotate as annotate_module
from dataset_tools.annotate import AnnotateOptions, annotate, annotate_arrays
from dataset_tools.hand.bones import estimate_bone_lengths, load_subject
from dataset_tools.keypoints.keypoints2d import CameraKeypoints, TakeKeypoints, write_keypoints_h5
from dataset_tools.simulated_detector import SimulatedDetector, simulated_take_keypoints
from dataset_tools.sync import frame_groups
from dataset_tools.triangulation import triangulate_frames
from manus_capture.cli import cli
from manus_core.dataset import FLAGS, read_dataset
from manus_core.errors import AnnotateError, SessionError, TakeError
from manus_core.frames_csv import HEADER, format_row
from manus_core.ground_truth import GroundTruth, TruthCameras, TruthFrames, TruthHand, write_record
from manus_core.rig_config import load_rig
from manus_core.session import open_session
from manus_core.skeleton import rodrigues
from manus_core.take import Take
from rig.layouts import make_rig
from rig.sim.cube import true_cameras
from rig.sim.hand import make_hand
from rig.sim.motion import make_motion
from rig.sim.objects import make_object

# The keypoints of these takes: the simulated detector on their ground truth, named as the ablation it is
SIMULATED = AnnotateOptions(keypoints="simulated")


def rotation_errors(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(np.swapaxes(rodrigues(a[:, :3]), 1, 2) @ rodrigues(b[:, :3])).magnitude()


def test_simulated_53_camera_grasp_meets_the_accuracy_targets():
    """2 px noise, 10% outliers, self-occlusion and the mug in the way, on the true cube53 cameras."""
    rig = true_cameras(make_rig("cube53", resolution=(1280, 720)))
    hand, mug = make_hand("s02"), make_object("mug")
    fps = 120.0
    # The subject's bone lengths, from a hand take of the same subject (30 poses/s is plenty).
    hand_take = make_motion("hand", hand, None, 3.0, seed=0).hand_angles(np.arange(90) / 30.0)
    det = SimulatedDetector(noise_px=2.0, outlier_rate=0.1, seed=1)
    Xh, eh = triangulate_frames(rig, det.detect(rig, hand.skeleton.forward(hand_take)))
    bones = estimate_bone_lengths(Xh, eh).bone_lengths
    assert np.abs(bones - hand.skeleton.bone_lengths).max() < 1e-3

    grasp = make_motion("grasp", hand, mug, 1.5, seed=0)
    t = np.arange(int(1.5 * fps)) / fps
    truth = grasp.hand_angles(t)
    joints = hand.skeleton.forward(truth)
    pose = mug.resting_pose()
    kp = SimulatedDetector(noise_px=2.0, outlier_rate=0.1, seed=2).detect(
        rig, joints, occluder=lambda f, o, d: mug.intersect(o, d, pose)[0])
    assert 0.4 < (kp[..., 2] > 0).mean() < 0.8      # occlusion is really there
    out = annotate_arrays(rig, kp, np.rint(1e9 * t).astype(np.int64), bones)

    tri = np.linalg.norm(out["keypoints3d"] - joints, axis=-1)
    assert np.isfinite(tri).all() and tri.mean() < 3e-3
    assert np.linalg.norm(out["fitted"] - joints, axis=-1).mean() < 4e-3
    filtered_joints = hand.skeleton.forward(out["joint_angles"])
    assert np.linalg.norm(filtered_joints - joints, axis=-1).mean() < 4e-3
    # Angles compared where they are observable: every joint was triangulated in every frame
    # here, so all 20 finger angles are; the global rotation by the angle between the rotations
    # (rotation vectors near a half turn have two forms, see docs/annotate.md).
    for angles in (out["joint_angles_raw"], out["joint_angles"]):
        assert np.isfinite(angles).all()
        fingers_rms = np.degrees(np.sqrt(np.mean((angles[:, 6:] - truth[:, 6:]) ** 2)))
        rotation_rms = np.degrees(np.sqrt(np.mean(rotation_errors(angles, truth) ** 2)))
        assert fingers_rms < 3.0 and rotation_rms < 3.0
    assert (out["flags"] & FLAGS["no_hand"] == 0).all() and np.nanmax(out["ik_residual_m"]) < 5e-3


# --- takes on disk ---------------------------------------------------------------------------------

def write_sim_take(folder: Path, rig, hand, motion, fps: float, n_frames: int, kind: str, seed: int = 0,
                   phase_ms: float = 0.5, drop: tuple = ()) -> np.ndarray:
    """A simulated take in the on-disk format (take.json, frames.csv, ground_truth.h5), without
    rendering: the keypoints come from the simulated detector. Returns the true joints (F,21,3)."""
    folder.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    period = 1e9 / fps
    ticks = 10**9 + np.arange(n_frames) * period
    exposure = np.rint(ticks[None] + rng.uniform(0, phase_ms * 1e6, len(rig))[:, None]).astype(np.int64)
    dropped = np.zeros((len(rig), n_frames), bool)
    for c, k in drop:
        dropped[c, k] = True
    angles = motion.hand_angles((ticks - ticks[0]) / 1e9)
    joints = hand.skeleton.forward(angles)
    with h5py.File(folder / "ground_truth.h5", "w") as f:
        write_record(f, TruthCameras(rig.ids, rig.K, rig.dist, rig.R, rig.t, rig.size))
        write_record(f, TruthFrames(np.rint(ticks).astype(np.int64), exposure, dropped))
        write_record(f, TruthHand(angles, joints, hand.skeleton.bone_lengths))
    rows = [HEADER + "\n"]
    for c, cam in enumerate(rig.ids):
        for k in np.flatnonzero(~dropped[c]):
            rows.append(format_row(cam, k, exposure[c, k] + 777, exposure[c, k] + int(2e6 + rng.exponential(3e5)),
                                   9000, ""))
    (folder / "frames.csv").write_text("".join(rows))
    (folder / "take.json").write_text(json.dumps({"kind": kind, "cameras": list(rig.ids), "fps": fps,
                                                  "status": "complete"}))
    return joints


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """A session of subject s03 (a hand take and a grasp take) on 12 cameras, and its calibration."""
    root = tmp_path_factory.mktemp("annotate")
    config = make_rig("cube53", cameras=12, resolution=(640, 360))
    rig = true_cameras(config)
    rig.save(root / "calib" / "cameras.json")
    hand = make_hand("s03")
    open_session(root / "S1", config, subject="s03", operator="test")  # session.toml as the recorder writes it
    write_sim_take(root / "S1" / "hand_01", rig, hand, make_motion("hand", hand, None, 3.0), 20.0, 60, "hand")
    joints = write_sim_take(root / "S1" / "grasp_01", rig, hand, make_motion("grasp", hand, make_object("box"), 1.0),
                            60.0, 60, "grasp", seed=1, drop=((0, 5), (3, 9)))
    return {"root": root, "rig": rig, "hand": hand, "grasp_joints": joints,
            "takes": [root / "S1" / "hand_01", root / "S1" / "grasp_01"]}


def dataset_arrays(path: Path) -> dict[str, dict[str, np.ndarray]]:
    ds = read_dataset(path)
    return {k: {n: v for n, v in vars(ds[k]).items() if isinstance(v, np.ndarray)} for k in ds.takes}


@pytest.fixture(scope="module")
def inline_result(session, tmp_path_factory):
    out = tmp_path_factory.mktemp("inline") / "DATASET.h5"
    summary = annotate(session["takes"], session["root"] / "calib", out, SIMULATED)
    return out, summary


def test_takes_on_disk_become_a_dataset_with_the_subjects_bones(session, inline_result):
    out, summary = inline_result
    assert summary.annotated == ["S1/hand_01", "S1/grasp_01"] and not summary.failed
    subject = session["root"] / "S1" / "subjects" / "s03.json"
    assert summary.subjects == {"S1": str(subject)}
    bones = load_subject(subject)
    assert np.abs(bones.bone_lengths - session["hand"].skeleton.bone_lengths).max() < 1e-3
    assert bones.takes == ["hand_01"]
    ds = read_dataset(out)
    grasp = ds["S1/grasp_01"]
    assert grasp.attrs["bone_source"] == "subject:S1/subjects/s03.json (from hand_01)"
    assert grasp.attrs["keypoint_source"].startswith("simulated:noise_px=2.0")
    assert grasp.attrs["kind"] == "grasp" and grasp.cameras == session["rig"].ids
    np.testing.assert_allclose(grasp.bone_lengths, bones.bone_lengths)
    # Frame groups: one per tick, and the two dropped frames leave their cameras empty there.
    assert len(grasp.frame_ns) == 60
    np.testing.assert_allclose(np.diff(grasp.frame_ns), 1e9 / 60, atol=1)
    assert grasp.frame_index[5, 0] == -1 and grasp.frame_index[9, 3] == -1
    assert grasp.frame_index[6, 0] == 5 and grasp.frame_index[59, 5] == 59
    assert set(np.flatnonzero(grasp.flags & FLAGS["incomplete_group"])) == {5, 9}
    truth = session["grasp_joints"]
    assert np.nanmean(np.linalg.norm(grasp.keypoints3d - truth, axis=-1)) < 3e-3
    assert np.nanmean(np.linalg.norm(grasp.fitted_joints(False) - truth, axis=-1)) < 4e-3


def test_dask_and_the_process_pool_give_the_inline_result(session, inline_result, tmp_path):
    from distributed import LocalCluster

    reference = dataset_arrays(inline_result[0])
    bones = session["root"] / "S1" / "subjects" / "s03.json"      # written by the inline run
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        summary = annotate(session["takes"], session["root"] / "calib", tmp_path / "dask.h5", SIMULATED,
                           scheduler=cluster.scheduler_address)
    assert sorted(summary.annotated) == ["S1/grasp_01", "S1/hand_01"] and summary.subjects["S1"] == str(bones)
    pooled = annotate(session["takes"], session["root"] / "calib", tmp_path / "pool.h5", SIMULATED, workers=2)
    assert not pooled.failed
    for path in (tmp_path / "dask.h5", tmp_path / "pool.h5"):
        other = dataset_arrays(path)
        assert other.keys() == reference.keys()
        for key in reference:
            for name, value in reference[key].items():
                # the same to rounding: a worker process's BLAS may split a sum over other threads
                # than this process's (measured: 1e-16 relative, with OPENBLAS_NUM_THREADS=1 bit-equal)
                np.testing.assert_allclose(other[key][name], value, rtol=1e-9, atol=1e-12,
                                           err_msg=f"{path.name} {key} {name}")


def test_an_interrupted_run_resumes_with_the_takes_it_had_not_finished(session, inline_result, tmp_path,
                                                                        monkeypatch):
    out = tmp_path / "DATASET.h5"
    real = annotate_module.annotate_take
    calls: list[str] = []

    def interrupted(task):
        if task.key == "S1/grasp_01":
            raise KeyboardInterrupt
        calls.append(task.key)
        return real(task)

    monkeypatch.setattr(annotate_module, "annotate_take", interrupted)
    with pytest.raises(KeyboardInterrupt):
        annotate(session["takes"], session["root"] / "calib", out, SIMULATED)
    assert not out.exists() and calls == ["S1/hand_01"]
    assert len(list((tmp_path / ".DATASET.h5.parts").glob("*.h5"))) == 1

    def counting(task):
        calls.append(task.key)
        return real(task)

    monkeypatch.setattr(annotate_module, "annotate_take", counting)
    summary = annotate(session["takes"], session["root"] / "calib", out, SIMULATED)
    assert calls == ["S1/hand_01", "S1/grasp_01"]          # the hand take was not done again
    assert summary.resumed == ["S1/hand_01"] and summary.annotated == ["S1/grasp_01"]
    reference, resumed = dataset_arrays(inline_result[0]), dataset_arrays(out)
    for key in reference:
        for name, value in reference[key].items():
            np.testing.assert_array_equal(resumed[key][name], value)
    # A third run has nothing left to do.
    again = annotate(session["takes"], session["root"] / "calib", out, SIMULATED)
    assert again.annotated == [] and sorted(again.resumed) == ["S1/grasp_01", "S1/hand_01"]


def test_keypoint_file_and_given_frame_groups(session, tmp_path):
    """keypoints2d.h5 (as `detect` writes it) is read per camera frame index, and frame groups from
    the sync stage are used as given."""
    take_dir = tmp_path / "S2" / "grasp_02"
    rig, hand = session["rig"], session["hand"]
    joints = write_sim_take(take_dir, rig, hand, make_motion("grasp", hand, make_object("sphere"), 0.5), 60.0, 30,
                            "grasp", seed=4, phase_ms=0.0)
    take = Take(take_dir)
    det = SimulatedDetector(noise_px=1.0, outlier_rate=0.05, seed=9).detect(rig, joints)   # (30,C,21,3)
    # Camera 2's frames are stored in another order than the groups: the frame index maps them.
    cams = {cam: CameraKeypoints(det[:, c].astype(np.float32), np.zeros((30, 4), np.float32),
                                 np.zeros(30, np.float32)) for c, cam in enumerate(rig.ids)}
    write_keypoints_h5(take_dir / "keypoints2d.h5", TakeKeypoints(cams, "simulated", "-", "test"))
    found = frame_groups(take)
    frame_ns, frame_index = found.frame_ns, found.frame_index
    groups = {str(take_dir): (frame_ns[5:], frame_index[5:])}
    summary = annotate([take_dir], session["root"] / "calib", tmp_path / "D.h5", bones=session["hand"].skeleton.bone_lengths,
                       groups=groups, options=AnnotateOptions(keypoints="file"))
    assert not summary.failed
    ann = read_dataset(tmp_path / "D.h5")["S2/grasp_02"]
    assert ann.attrs["frame_groups"] == "given" and ann.attrs["bone_source"] == "given"
    assert ann.attrs["keypoint_source"] == "file:keypoints2d.h5 (model simulated)"
    np.testing.assert_array_equal(ann.frame_ns, frame_ns[5:])
    np.testing.assert_allclose(ann.keypoints2d, det[5:].astype(np.float32), equal_nan=True)
    assert np.nanmean(np.linalg.norm(ann.keypoints3d - joints[5:], axis=-1)) < 2e-3


def test_bad_input_gives_clear_errors_or_marked_frames(session, inline_result, tmp_path):
    # inline_result: the run that writes S1/subjects/s03.json, which --bones below reads
    root, rig = session["root"], session["rig"]
    with pytest.raises(AnnotateError, match="no such calibration"):
        annotate(session["takes"], tmp_path / "nowhere", tmp_path / "D.h5")
    # A calibration with one of the take's cameras: nothing to triangulate with (a partial
    # calibration of two or more is used, test_dataset_provenance.py).
    rig.subset(rig.ids[5:6]).save(tmp_path / "partial" / "cameras.json")
    with pytest.raises(TakeError, match=re.escape(f"1 of the take's cameras ({rig.ids[5]}) in the calibration")):
        annotate(session["takes"], tmp_path / "partial", tmp_path / "D.h5")
    assert not (tmp_path / "D.h5").exists()

    # Frames with too few views: NaN and flagged, never filled in.
    truth = session["grasp_joints"][:20]
    kp = SimulatedDetector(noise_px=1.0, outlier_rate=0.0, self_occlusion=False, seed=5).detect(rig, truth)
    assert (kp[..., 2] > 0).all()
    kp[5:8, 1:] = (np.nan, np.nan, 0.0)                 # one camera left: nothing can be triangulated
    kp[10, 2:, :10] = (np.nan, np.nan, 0.0)             # joints 0-9 in two views only, 10-20 in all
    kp[11, 1:, 17:] = (np.nan, np.nan, 0.0)             # the pinky in one view: its angles unknown
    out = annotate_arrays(rig, kp, np.arange(20) * 16_666_667, session["hand"].skeleton.bone_lengths)
    assert np.isnan(out["keypoints3d"][5:8]).all() and np.isnan(out["joint_angles_raw"][5:8]).all()
    assert np.isnan(out["joint_angles"][5:8]).all() and np.isnan(out["ik_residual_m"][5:8]).all()
    assert (out["flags"][5:8] & FLAGS["no_hand"]).all() and (out["keypoints3d_views"][5:8] == 0).all()
    assert (out["keypoints3d_views"][10, :10] == 2).all() and not out["flags"][10] & FLAGS["no_hand"]
    assert np.isnan(out["keypoints3d"][11, 17:]).all() and out["flags"][11] & FLAGS["missing_joints"]
    assert np.isnan(out["joint_angles_raw"][11, 22:26]).all() and np.isfinite(out["joint_angles_raw"][11, :22]).all()
    good = np.setdiff1d(np.arange(20), [5, 6, 7, 11])
    assert np.isfinite(out["joint_angles_raw"][good]).all() and not (out["flags"][good] & FLAGS["no_hand"]).any()

    # All keypoints missing: the take fails with a clear message, the others are written.
    empty = tmp_path / "S9" / "grasp_empty"
    write_sim_take(empty, rig, session["hand"], make_motion("grasp", session["hand"], make_object("box"), 0.3),
                   60.0, 18, "grasp")
    nothing = {cam: CameraKeypoints(np.full((18, 21, 3), np.nan, np.float32), np.zeros((18, 4), np.float32),
                                    np.zeros(18, np.float32)) for cam in rig.ids}
    write_keypoints_h5(empty / "keypoints2d.h5", TakeKeypoints(nothing, "none", "-", "test"))
    # the good take beside it, with its keypoints in a file too (the simulated detector's, per camera frame)
    good = tmp_path / "S1" / "grasp_01"
    shutil.copytree(session["takes"][1], good)
    counts = np.array([Take(good).frame_count(cam) for cam in rig.ids])
    rows = np.arange(counts.max())[:, None]
    per_frame = np.where(rows < counts, rows, -1)                   # row k: each camera's k-th frame
    kp = simulated_take_keypoints(Take(good), per_frame, SimulatedDetector(seed=2)).astype(np.float32)
    write_keypoints_h5(good / "keypoints2d.h5", TakeKeypoints(
        {cam: CameraKeypoints(kp[:n, c], np.zeros((n, 4), np.float32), np.zeros(n, np.float32))
         for c, (cam, n) in enumerate(zip(rig.ids, counts))}, "simulated", "-", "test"))
    result = CliRunner().invoke(cli, ["annotate", str(empty), str(good), "--calib", str(root / "calib"),
                                      "-o", str(tmp_path / "E.h5"), "--bones", str(root / "S1" / "subjects" / "s03.json")])
    assert result.exit_code == 2, result.output
    assert "no joint could be triangulated in any of the 18 frames" in result.output
    assert "Traceback" not in result.output
    assert read_dataset(tmp_path / "E.h5").takes == ["S1/grasp_01"]
    result = CliRunner().invoke(cli, ["annotate", str(empty), "--calib", str(tmp_path / "nowhere"), "-o",
                                      str(tmp_path / "F.h5")])
    assert result.exit_code == 2 and "no such calibration" in result.output

    # A session.toml that is not one: the recorder's reader names the file, nothing is written.
    (tmp_path / "S9" / "session.toml").write_text("[session\nsubject = 's03'\n")
    with pytest.raises(SessionError, match=re.escape(f"{tmp_path / 'S9' / 'session.toml'}: not valid TOML")):
        annotate([empty], root / "calib", tmp_path / "G.h5")
    assert not (tmp_path / "G.h5").exists()


def test_cli_annotate_then_stats(session, tmp_path):
    out = tmp_path / "D.h5"
    runner = CliRunner()
    result = runner.invoke(cli, ["annotate", *map(str, session["takes"]), "--calib", str(session["root"] / "calib"),
                                 "-o", str(out), "--workers", "1", "--keypoints", "simulated"])
    assert result.exit_code == 0, result.output
    assert "2 takes annotated, 0 kept from before, 0 failed; 120 frames, hand fitted in 120" in result.output
    result = runner.invoke(cli, ["stats", str(out), "--json", str(tmp_path / "stats.json")])
    assert result.exit_code == 0, result.output
    assert "S1/grasp_01" in result.output and "2 takes, 120 frames, hand fitted in 120 (100.0%)" in result.output
    png = tmp_path / "D.aperture.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    stats = json.loads((tmp_path / "stats.json").read_text())
    grasp = stats["S1/grasp_01"]
    assert grasp["frames"] == 60 and grasp["frames_fitted"] == 60 and grasp["flags"]["incomplete_group"] == 2
    assert 1.0 < grasp["reprojection_px_median"] < 4.0 and grasp["ik_residual_mm_median"] < 3.0
    assert 2.0 <= grasp["views_per_joint_mean"] <= 12
    # The plot exists now: a second run needs --force.
    result = runner.invoke(cli, ["stats", str(out)])
    assert result.exit_code == 2 and "exists" in result.output
    assert runner.invoke(cli, ["stats", str(out), "--force"]).exit_code == 0


def test_recorded_sim_take_end_to_end(tmp_path):
    """rig init -> record -> sync-report -> annotate (the report's frame groups, simulated detector)
    -> close to the truth."""
    runner = CliRunner()
    rig_file = tmp_path / "rig.toml"
    # triggered cameras expose at the tick, so the ticks' true joints are what every view saw
    assert runner.invoke(cli, ["rig", "init", "--cameras", "8", "--resolution", "320x180", "--sync",
                               "hardware-trigger", "-o", str(rig_file)]).exit_code == 0
    result = runner.invoke(cli, ["record", "--rig", str(rig_file), "--session", str(tmp_path / "S"), "--take", "g",
                                 "--kind", "grasp", "--duration", "0.3"])
    assert result.exit_code == 0, result.output   # recorded, and its sync check passed
    take = tmp_path / "S" / "g"
    assert json.loads((take / "sync_report.json").read_text())["verdict"] == "pass"
    true_cameras(load_rig(rig_file)).save(tmp_path / "cameras.json")
    out = tmp_path / "D.h5"
    result = runner.invoke(cli, ["annotate", str(take), "--calib", str(tmp_path / "cameras.json"),
                                 "-o", str(out), "--keypoints", "simulated"])
    assert result.exit_code == 0, result.output
    gt = GroundTruth.of_take(take)
    ann = read_dataset(out)["S/g"]
    assert ann.attrs["frame_groups"] == "sync (fitted device clocks), frame_groups.npz of the sync report"
    np.testing.assert_array_equal(ann.frame_index, frame_groups(take).frame_index)
    tick = gt.tick_at(ann.frame_ns)
    error = np.linalg.norm(ann.keypoints3d - gt.hand.joints3d[tick], axis=-1)
    # 2 px of detector noise is ~1 cm per view at 320x180 and 1 m; 8 views bring it to ~6 mm (measured 5.9)
    assert len(tick) >= 34 and np.nanmedian(error) < 0.008, np.nanmedian(error)


def test_a_scheduler_that_does_not_answer_is_named_within_ten_seconds(session, tmp_path):
    import socket
    import time

    from click.testing import CliRunner

    from manus_capture.cli import cli

    with socket.socket() as s:   # a free port, closed again: nothing answers there
        s.bind(("127.0.0.1", 0))
        address = f"tcp://127.0.0.1:{s.getsockname()[1]}"
    start = time.monotonic()
    res = CliRunner().invoke(cli, ["annotate", *map(str, session["takes"]), "--calib", str(session["root"] / "calib"),
                                   "--keypoints", "simulated", "--scheduler", address, "-o", str(tmp_path / "D.h5")])
    assert time.monotonic() - start < 10
    assert res.exit_code == 2 and f"the Dask scheduler {address} does not answer" in res.output, res.output
    assert "Traceback" not in res.output and not (tmp_path / "D.h5").exists()
