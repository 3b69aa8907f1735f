"""MANUS / BRICS releases both ways (issue 25): a simulated grasp take, annotated and masked, is
exported in the release layout and imported back; what comes back is compared with what went out
(cameras to 1e-6 px, timestamps to the microsecond, the very JPEG packets, keypoints, angles,
masks), MANUS's own way of reading the files is replayed on the export, and the pipeline's stages
run on the imported take. Bad releases are named, not half-imported."""

from __future__ import annotations

import json
import pickle
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from dataset_tools.release.brics_angles import euler_xyz_to_matrix, from_release, to_release
from dataset_tools.sync import RELEASE_METHOD, frame_groups
from dataset_tools.undistort import undistort_points
from manus_capture.cli import cli
from manus_core.cameras import CameraRig
from manus_core.dataset import add_arrays, read_dataset
from manus_core.ground_truth import GroundTruth
from manus_core.rotations import rotvec_to_matrix
from manus_core.take import Take

# MANUS's reader of optim_params.txt: numpy's loadtxt with this structured dtype, sorted by name
MANUS_DTYPE = [("cam_id", int), ("width", int), ("height", int), ("fx", float), ("fy", float), ("cx", float),
               ("cy", float), ("k1", float), ("k2", float), ("p1", float), ("p2", float), ("cam_name", "<U22"),
               ("qvecw", float), ("qvecx", float), ("qvecy", float), ("qvecz", float), ("tvecx", float),
               ("tvecy", float), ("tvecz", float)]


def run(*args: str, code: int = 0) -> str:
    res = CliRunner().invoke(cli, [str(a) for a in args])
    assert res.exit_code == code and "Traceback" not in res.output, res.output
    return res.output


@pytest.fixture(scope="module")
def source(tmp_path_factory) -> dict:
    """A recorded grasp take (6 cameras, 96x54, 1 s), its true cameras as the calibration (what is
    compared here is the round trip, not the calibration), annotated with the simulated detector,
    with disc masks on every third frame group."""
    root = tmp_path_factory.mktemp("brics")
    run("rig", "init", "--cameras", "6", "--resolution", "96x54", "--fps", "30", "-o", root / "rig.toml")
    run("record", "--rig", root / "rig.toml", "--session", root / "S", "--take", "g", "--kind", "grasp",
        "--duration", "1", "--no-sync-check")
    take = root / "S" / "g"
    GroundTruth.of_take(take).cameras.rig().save(root / "cal" / "cameras.json")
    run("annotate", take, "--calib", root / "cal", "-o", root / "S" / "DATASET.h5", "--keypoints", "simulated")
    ann = read_dataset(root / "S" / "DATASET.h5")["S/g"]
    rows = np.arange(0, len(ann.frame_ns), 3)
    centre = np.random.default_rng(0).uniform([20, 10], [76, 44], (len(rows), len(ann.cameras), 2))
    yy, xx = np.mgrid[0:54, 0:96]
    d2 = (xx - centre[..., 0, None, None]) ** 2 + (yy - centre[..., 1, None, None]) ** 2
    masks = {"masks/hand": d2 < 100, "masks/object": (d2 > 150) & (d2 < 300), "masks/frame_ns": ann.frame_ns[rows]}
    add_arrays(root / "S" / "DATASET.h5", "S/g", masks, {"mask_cameras": list(ann.cameras)}, stage="segment")
    out = run("export", "brics", take, "--calib", root / "cal", "-o", root / "rel")
    run("import", "brics", root / "rel", "-o", root / "I")
    return {"root": root, "take": take, "ann": ann, "masks": masks, "rows": rows, "export_line": out,
            "capture": next((root / "rel" / "grasps").iterdir()), "imported": root / "I" / "g"}


def exported_groups(ann) -> np.ndarray:
    """The annotation rows the export wrote: those with a frame of every camera."""
    return np.flatnonzero((ann.frame_index >= 0).all(1))


def test_export_writes_what_manus_reads(source: dict) -> None:
    capture, ann = source["capture"], source["ann"]
    assert capture.name.endswith("_session_g") and capture.parent.name == "grasps"
    params = np.sort(np.loadtxt(source["root"] / "rel" / "optim_params.txt", dtype=MANUS_DTYPE), order="cam_name")
    rig = CameraRig.load(source["root"] / "cal" / "cameras.json")
    assert list(params["cam_name"]) == sorted(rig.ids)
    i = rig.index(str(params["cam_name"][0]))
    assert params["fx"][0] == rig.K[i, 0, 0] and params["tvecz"][0] == rig.t[i, 2]
    cams = sorted(p.name for p in (capture / "synced").iterdir())
    assert cams == sorted(rig.ids)
    done = exported_groups(ann)
    assert f"{len(done)} frames" in source["export_line"]
    for cam in cams:   # one timestamp line per frame of each video, index-aligned across cameras
        lines = (capture / "synced" / cam / f"{cam}_synced_files.txt").read_text().splitlines()
        assert len(lines) == len(done) and all(len(line.split(" ")) == 3 for line in lines)
    kp = json.loads((capture / "pose_dumps" / "keypoints_2d" / cams[0] / "00000000.json").read_text())
    assert np.shape(kp) == (21, 3)
    pose = json.loads((capture / "pose_dumps" / "joint_angles" / "00000000.json").read_text())
    assert np.shape(pose["angles"]) == (21, 3) and np.shape(pose["translation"]) == (3,)
    assert np.shape(json.loads((capture / "pose_dumps" / "bone_lens.json").read_text())) == (20,)
    with h5py.File(source["root"] / "rel" / "actions_hdf5" / "g.hdf5", "r") as f:
        assert sorted(f["K"]) == sorted(rig.ids)
        assert np.allclose(f[f"extr/{rig.ids[0]}"][()], np.hstack([rig.R[0], rig.t[0][:, None]]))
        frame = next(iter(f["frames"].values()))
        for cam, crop in frame["images"].items():
            x0, y0, x1, y1 = frame["bbox"][cam][()]
            assert crop.dtype == np.uint8 and crop.shape == (y1 - y0, x1 - x0, 4)
            assert 0 < (crop[..., 3] == 255).sum() < crop[..., 3].size   # the hand, with a margin around it


def test_import_gives_back_what_was_exported(source: dict) -> None:
    take, imported, ann = Take(source["take"]), Take(source["imported"]), source["ann"]
    done = exported_groups(ann)
    assert imported.meta["kind"] == "grasp" and not (source["imported"] / "cams").exists()
    assert set(imported.meta["videos"]) == set(take.cameras)          # read where they lie
    rig = CameraRig.load(source["root"] / "cal" / "cameras.json")
    back = CameraRig.load(source["root"] / "I" / "calibration" / "cameras.json").subset(rig.ids)
    X = np.random.default_rng(1).uniform(-0.15, 0.15, (500, 3))
    assert np.nanmax(np.abs(back.project(X) - rig.project(X))) < 1e-6
    for c, cam in enumerate(ann.cameras):
        k = ann.frame_index[done, c]
        t_host = take.camera_frames(cam)["t_host_ns"][k]
        assert np.array_equal(imported.camera_frames(cam)["t_host_ns"], t_host // 1000 * 1000)
        original = [p.tobytes() for i, p in enumerate(take.packets(cam)) if i in set(k.tolist())]
        assert [p.tobytes() for p in imported.packets(cam)] == original
    groups = frame_groups(imported)
    assert groups.method == RELEASE_METHOD and len(groups.frame_ns) == len(done)
    got = read_dataset(source["root"] / "I" / "DATASET.h5")["I/g"]
    assert got.cameras == ann.cameras
    sent = ann.keypoints2d[done].astype(np.float64)
    seen = got.keypoints2d[..., 2] > 0
    # the release keeps undistorted pixels: a detector's outlier far outside the image, beyond where
    # the lens model inverts, has none and goes out with confidence 0; every other point comes back
    rig = rig.subset(ann.cameras)
    xy = undistort_points(rig, sent[..., :2].transpose(1, 0, 2, 3).reshape(len(rig), -1, 2))
    invertible = np.isfinite(xy).all(-1).reshape(len(rig), len(done), 21).transpose(1, 0, 2)
    assert np.array_equal(seen, (sent[..., 2] > 0) & invertible)
    lost = (sent[..., 2] > 0) & ~invertible
    outside = (sent[..., :2] < 0).any(-1) | (sent[..., :2] >= rig.size[None, :, None]).any(-1)
    assert lost.sum() < 0.05 * (sent[..., 2] > 0).sum() and outside[lost].all()
    assert np.isnan(got.keypoints2d[..., :2][~seen]).all() and (got.keypoints2d[..., 2][~seen] == 0).all()
    assert np.abs(got.keypoints2d[..., :2][seen] - sent[..., :2][seen]).max() < 1e-3   # float32 storage
    assert np.allclose(got.keypoints3d, ann.keypoints3d[done], equal_nan=True, atol=1e-12)
    assert np.allclose(got.bone_lengths, ann.bone_lengths, atol=1e-12)
    # JSON has no NaN: a frame whose fit left a finger undetermined has no pose file and comes back NaN
    whole = np.isfinite(ann.joint_angles_raw[done]).all(1)
    assert whole.sum() > len(done) / 2 and np.isnan(got.joint_angles_raw[~whole]).all()
    a, b = got.joint_angles_raw[whole], ann.joint_angles_raw[done][whole]
    assert np.abs(a[:, 3:] - b[:, 3:]).max() < 1e-12
    assert np.abs(rotvec_to_matrix(a[:, :3]) - rotvec_to_matrix(b[:, :3])).max() < 1e-12
    assert got.attrs["filter"]["source"].startswith("release:joint_angles")


def test_masks_come_back(source: dict) -> None:
    ann, masks = source["ann"], source["masks"]
    done = exported_groups(ann)
    with h5py.File(source["root"] / "I" / "DATASET.h5", "r") as f:
        g = f["I/g"]
        back_ns, hand, obj = g["masks/frame_ns"][()], g["masks/hand"][()], g["masks/object"][()]
    got_rows = np.searchsorted(read_dataset(source["root"] / "I" / "DATASET.h5")["I/g"].frame_ns, back_ns)
    sent = [i for i, r in enumerate(source["rows"]) if r in set(done.tolist())]
    assert len(back_ns) == len(sent) > 0
    assert np.array_equal(done[got_rows], source["rows"][sent])
    assert np.array_equal(hand, masks["masks/hand"][sent]) and np.array_equal(obj, masks["masks/object"][sent])


def test_the_pipeline_runs_on_the_imported_take(source: dict) -> None:
    """sync-report keeps the release's groups; annotate triangulates the imported 2D keypoints (from
    the keypoints2d.h5 the import wrote) into the same joints as the original annotation."""
    imported = source["imported"]
    out = run("sync-report", imported)
    assert ": pass (6 cameras" in out
    assert json.loads((imported / "sync_report.json").read_text())["frame_groups"].endswith(f"({RELEASE_METHOD}, kept)")
    run("annotate", imported, "--calib", source["root"] / "I" / "calibration", "-o", source["root"] / "I2.h5")
    again = read_dataset(source["root"] / "I2.h5")["I/g"]
    sent = source["ann"].keypoints3d[exported_groups(source["ann"])]
    found = np.isfinite(sent).all(-1)
    assert np.array_equal(np.isfinite(again.keypoints3d).all(-1), found) and found.mean() > 0.5
    assert np.linalg.norm(again.keypoints3d - sent, axis=-1)[found].max() < 1e-6


def test_copy_remuxes_without_reencoding(source: dict, tmp_path: Path) -> None:
    run("import", "brics", source["root"] / "rel", "-o", tmp_path / "C", "--copy")
    copied, referenced = Take(tmp_path / "C" / "g"), Take(source["imported"])
    assert copied.meta["videos"] == {}
    for cam in copied.cameras:
        assert copied.video_path(cam).parent.name == "cams"
        assert [p.tobytes() for p in copied.packets(cam)] == [p.tobytes() for p in referenced.packets(cam)]


def test_a_broken_release_is_named_and_the_rest_imported(source: dict, tmp_path: Path, monkeypatch) -> None:
    rel = tmp_path / "rel"
    shutil.copytree(source["root"] / "rel", rel)
    capture = next((rel / "grasps").iterdir())
    cams = sorted(p.name for p in (capture / "synced").iterdir())
    # a camera without its video, a video of no camera, short and backward timestamps, and a pickle
    shutil.rmtree(capture / "synced" / cams[0])
    shutil.copytree(capture / "synced" / cams[1], capture / "synced" / "stray")
    (capture / "synced" / "stray" / f"{cams[1]}.avi").rename(capture / "synced" / "stray" / "stray.avi")
    short = capture / "synced" / cams[2] / f"{cams[2]}_synced_files.txt"
    lines = short.read_text().splitlines()
    short.write_text("\n".join(lines[:-4]) + "\n")
    back = capture / "synced" / cams[3] / f"{cams[3]}_synced_files.txt"
    lines = back.read_text().splitlines()
    lines[5] = lines[5].rsplit(" ", 1)[0] + " " + lines[3].rsplit(" ", 1)[1]
    back.write_text("\n".join(lines) + "\n")
    (capture / "meta_data.pkl").write_bytes(pickle.dumps({"x": 1}))
    monkeypatch.setattr(pickle, "load", lambda *a, **k: pytest.fail("a release's pickle was loaded"))
    monkeypatch.setattr(pickle, "loads", lambda *a, **k: pytest.fail("a release's pickle was loaded"))
    out = run("import", "brics", rel, "-o", tmp_path / "B")
    assert f"left out: {cams[0]}: in the cameras file, no video" in out
    assert "left out: stray: a video, not in the cameras file" in out
    assert f"{cams[2]}: 4 frames after the last timestamp line dropped" in out
    assert f"{cams[3]}: 1 frames whose timestamp is not later than an earlier one dropped" in out
    take = Take(tmp_path / "B" / "g")
    assert cams[0] not in take.cameras and "stray" not in take.cameras
    assert set(take.meta["videos"]) == set(cams[1:]) - {cams[2], cams[3]}    # those two re-muxed
    assert take.frame_count(cams[2]) == len(lines) - 4 and take.frame_count(cams[3]) == len(lines) - 1
    assert 5 not in take.camera_frames(cams[3])["seq"]          # the dropped frame is a sequence gap
    assert len(list(take.packets(cams[3]))) == take.frame_count(cams[3])
    out = run("import", "brics", rel, "-o", tmp_path / "strict", "--strict", code=2)
    assert out.count("\n") == 1 and f"{cams[0]}: in the cameras file, no video" in out
    assert not (tmp_path / "strict" / "g").exists()


def test_not_a_release(tmp_path: Path) -> None:
    (tmp_path / "x").mkdir()
    out = run("import", "brics", tmp_path / "x", "-o", tmp_path / "S", code=2)
    assert out.count("\n") == 1 and "not a MANUS/BRICS release: no synced/ folder" in out
    (tmp_path / "x" / "synced" / "cam0").mkdir(parents=True)
    out = run("import", "brics", tmp_path / "x", "-o", tmp_path / "S", code=2)
    assert "no optim_params.txt" in out and "--cameras" in out


def test_angles_map_both_ways_in_blenders_convention() -> None:
    rng = np.random.default_rng(2)
    angles = np.concatenate([rng.uniform(-1, 1, (50, 3)), rng.uniform(-0.2, 0.2, (50, 3)),
                             rng.uniform(-0.3, 1.2, (50, 20))], axis=1)
    translation, eulers = to_release(angles)
    assert eulers.shape == (50, 21, 3) and np.all(eulers[:, [1, 5, 9, 13, 17]] == 0)   # no DOF there
    back = from_release(translation, eulers)
    assert np.abs(back - angles).max() < 1e-12
    a, b, c = 0.3, -0.2, 0.5      # Blender 'XYZ': R = Rz(c) @ Ry(b) @ Rx(a)
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    assert np.allclose(euler_xyz_to_matrix(np.array([a, b, c])), rz @ ry @ rx, atol=1e-15)
