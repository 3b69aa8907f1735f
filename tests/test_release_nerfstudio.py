"""One frame group exported for nerfstudio and gsplat (dataset_tools.release.nerfstudio): the
cameras read back from transforms.json alone, and from sparse/0 through pycolmap, project points
where the true cameras of a simulated take do; images and masks are the group's frames.

The take is recorded once with `record` on the simulated cube, as tests/test_sync_faults.py does."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from click.testing import CliRunner

from dataset_tools.release.nerfstudio import write_frame_group
from dataset_tools.sync import frame_groups
from manus_capture.cli import cli
from manus_core.cameras import CameraRig
from manus_core.errors import InputError, OutputExists
from manus_core.ground_truth import GroundTruth
from manus_core.take import Take

# near the cube's centre (the world origin), where every camera looks
POINTS = np.random.default_rng(7).uniform(-0.05, 0.05, size=(200, 3))


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> tuple[Take, CameraRig]:
    """A 0.3 s take of 4 simulated 64x36 cameras and its true cameras."""
    root = tmp_path_factory.mktemp("release")
    runner = CliRunner()
    res = runner.invoke(cli, ["rig", "init", "--cameras", "4", "--resolution", "64x36", "--fps", "30",
                              "-o", str(root / "rig.toml")])
    assert res.exit_code == 0, res.output
    res = runner.invoke(cli, ["record", "--rig", str(root / "rig.toml"), "--session", str(root / "S"), "--take", "t",
                              "--kind", "hand", "--duration", "0.3", "--no-sync-check"])
    assert res.exit_code == 0, res.output
    take = root / "S" / "t"
    return Take(take), GroundTruth.of_take(take).cameras.rig()


def full_group(take: Take) -> int:
    """The first frame group every camera has a frame in."""
    index = frame_groups(take).frame_index
    return int(np.flatnonzero((index >= 0).all(axis=1))[0])


def make_masks(rig: CameraRig) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(3)
    return {cam: rng.random((int(h), int(w))) < 0.3 for cam, (w, h) in zip(rig.ids, rig.size)}


@pytest.fixture(scope="module")
def exported(recorded, tmp_path_factory) -> tuple[Path, int, dict, list]:
    """The full group written with masks: (out, group, masks, progress calls)."""
    take, rig = recorded
    out = tmp_path_factory.mktemp("export") / "ns"
    group, masks, calls = full_group(take), make_masks(rig), []
    path = write_frame_group(take, rig, group, out, masks=masks, progress=lambda *a: calls.append(a))
    assert path == out / "transforms.json"
    return out, group, masks, calls


def nerfstudio_project(frame: dict, X: np.ndarray) -> np.ndarray:
    """Pixels of X by a frame of transforms.json alone, in OpenCV's pixel grid (origin at the centre
    of the first pixel): nerfstudio's (and COLMAP's) grid starts at its corner, half a pixel away."""
    c2w = np.array(frame["transform_matrix"], dtype=np.float64)
    c2w[:3, 1:3] *= -1  # OpenGL camera axes (y up, z back) back to OpenCV's
    w2c = np.linalg.inv(c2w)
    K = np.array([[frame["fl_x"], 0, frame["cx"]], [0, frame["fl_y"], frame["cy"]], [0, 0, 1]], dtype=np.float64)
    dist = np.array([frame[k] for k in ("k1", "k2", "p1", "p2", "k3")], dtype=np.float64)
    px, _ = cv2.projectPoints(X, cv2.Rodrigues(w2c[:3, :3])[0], w2c[:3, 3], K, dist)
    return px.reshape(-1, 2) - 0.5


def test_transforms_json_projects_like_the_rig_and_points_at_the_frames(recorded, exported) -> None:
    take, rig = recorded
    out, group, masks, calls = exported
    doc = json.loads((out / "transforms.json").read_text())
    assert doc["camera_model"] == "OPENCV"
    frames = {Path(f["file_path"]).stem: f for f in doc["frames"]}
    assert list(frames) == list(take.cameras) == list(rig.ids)
    assert calls == [("export", i + 1, 4) for i in range(4)]
    groups = frame_groups(take)
    truth = rig.project(POINTS)
    assert np.isfinite(truth).all()
    for c, cam in enumerate(rig.ids):
        frame = frames[cam]
        assert frame["file_path"] == f"images/{cam}.png" and frame["mask_path"] == f"masks/{cam}.png"
        assert (frame["w"], frame["h"]) == (64, 36)
        assert np.abs(nerfstudio_project(frame, POINTS) - truth[c]).max() < 1e-6
        # the camera looks down its -z axis in nerfstudio's convention
        c2w = np.array(frame["transform_matrix"])
        assert np.allclose(c2w[3], [0, 0, 0, 1]) and np.allclose(c2w[:3, 3], rig.centers[c])
        assert np.dot(-c2w[:3, 2], -rig.centers[c]) > 0
        image = cv2.imread(str(out / frame["file_path"]), cv2.IMREAD_UNCHANGED)
        mask = cv2.imread(str(out / frame["mask_path"]), cv2.IMREAD_UNCHANGED)
        assert image.shape == (frame["h"], frame["w"], 3) and mask.shape == (frame["h"], frame["w"])
        assert np.array_equal(image, take.read_frame(cam, int(groups.frame_index[group, c])))
        assert mask.dtype == np.uint8 and np.array_equal(mask, np.where(masks[cam], 255, 0))
    note = doc["manus_capture"]
    assert note["group"] == group and note["cameras_without_frame"] == []
    assert note["frame_ns"] == int(groups.frame_ns[group])


def test_colmap_model_holds_the_same_cameras(recorded, exported) -> None:
    _, rig = recorded
    out = exported[0]
    rec = pycolmap.Reconstruction(out / "sparse" / "0")
    names = sorted(image.name for image in rec.images.values())
    assert names == sorted(p.name for p in (out / "images").iterdir()) == sorted(f"{c}.png" for c in rig.ids)
    assert len(rec.points3D) == 0
    truth = rig.project(POINTS)
    for image in rec.images.values():
        c = rig.index(Path(image.name).stem)
        pose = image.cam_from_world()
        Rt = pose.matrix()
        assert np.abs(Rt[:, :3] - rig.R[c]).max() < 1e-9 and np.abs(Rt[:, 3] - rig.t[c]).max() < 1e-9
        camera = rec.cameras[image.camera_id]
        assert camera.model.name == "OPENCV" and (camera.width, camera.height) == (64, 36)
        fx, fy, cx, cy, k1, k2, p1, p2 = camera.params
        K = np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1]])
        assert np.abs(K - rig.K[c]).max() < 1e-9
        assert np.abs(np.array([k1, k2, p1, p2, 0.0]) - rig.dist[c]).max() < 1e-9
        px = camera.img_from_cam(pose * POINTS) - 0.5  # COLMAP's pixel grid starts at the first pixel's corner
        assert np.abs(px - truth[c]).max() < 1e-6


def test_only_cameras_of_both_rig_and_group_are_written(recorded, tmp_path) -> None:
    take, rig = recorded
    groups = frame_groups(take)
    # the free-running simulated cameras start out of phase: some group lacks a camera's frame
    partial = [g for g in range(len(groups.frame_ns)) if 0 < (groups.frame_index[g] < 0).sum() < len(rig)]
    assert partial
    group = partial[0]
    lacking = [cam for cam, k in zip(groups.cameras, groups.frame_index[group]) if k < 0]
    subset = rig.subset(rig.ids[1:])
    path = write_frame_group(take, subset, group, tmp_path / "ns")
    doc = json.loads(path.read_text())
    written = [Path(f["file_path"]).stem for f in doc["frames"]]
    assert written == [c for c in subset.ids if c not in lacking]
    assert doc["manus_capture"]["cameras_without_frame"] == [c for c in subset.ids if c in lacking]
    assert not (tmp_path / "ns" / "masks").exists() and all("mask_path" not in f for f in doc["frames"])
    assert sorted(p.name for p in (tmp_path / "ns" / "images").iterdir()) == sorted(f"{c}.png" for c in written)
    rec = pycolmap.Reconstruction(tmp_path / "ns" / "sparse" / "0")
    assert sorted(im.name for im in rec.images.values()) == sorted(f"{c}.png" for c in written)


def test_tangential_distortion_and_k3_survive_both_formats(recorded, tmp_path) -> None:
    """The simulated lenses have no p1, p2 or k3: a rig that has them (the images need not fit it)
    checks their order in transforms.json and that k3 makes sparse/0 FULL_OPENCV."""
    take, rig = recorded
    extra = np.array([0.0, 0.0, 0.0021, -0.0013, 0.0042])
    lens = CameraRig(rig.ids, rig.K, rig.dist + extra, rig.R, rig.t, rig.size)
    path = write_frame_group(take, lens, full_group(take), tmp_path / "ns")
    truth = lens.project(POINTS)
    for frame in json.loads(path.read_text())["frames"]:
        c = lens.index(Path(frame["file_path"]).stem)
        assert frame["k3"] == lens.dist[c, 4] and (frame["p1"], frame["p2"]) == tuple(lens.dist[c, 2:4])
        assert np.abs(nerfstudio_project(frame, POINTS) - truth[c]).max() < 1e-6
    rec = pycolmap.Reconstruction(tmp_path / "ns" / "sparse" / "0")
    for image in rec.images.values():
        c = lens.index(Path(image.name).stem)
        camera = rec.cameras[image.camera_id]
        assert camera.model.name == "FULL_OPENCV"
        assert np.abs(np.asarray(camera.params[4:9]) - lens.dist[c]).max() < 1e-9
        assert not np.any(camera.params[9:])
        px = camera.img_from_cam(image.cam_from_world() * POINTS) - 0.5
        assert np.abs(px - truth[c]).max() < 1e-6


def test_bad_input_is_refused_with_the_file_named(recorded, tmp_path) -> None:
    take, rig = recorded
    count = len(frame_groups(take).frame_ns)
    for group in (count, -1):
        with pytest.raises(InputError, match=f"no frame group {group}: the take has {count} frame groups") as err:
            write_frame_group(take, rig, group, tmp_path / "a")
        assert str(take.path) in str(err.value) and "\n" not in str(err.value)
    assert not (tmp_path / "a").exists()

    out = tmp_path / "b"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(OutputExists) as err:
        write_frame_group(take, rig, full_group(take), out)
    assert str(out) in str(err.value) and sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    assert write_frame_group(take, rig, full_group(take), out, force=True).is_file()
    assert (out / "notes.txt").read_text() == "mine"

    masks = make_masks(rig)
    del masks[rig.ids[2]]
    with pytest.raises(InputError, match=re.escape(f"not for camera '{rig.ids[2]}'")):
        write_frame_group(take, rig, full_group(take), tmp_path / "c", masks=masks)
    masks = {cam: m.astype(np.uint8) for cam, m in make_masks(rig).items()}
    with pytest.raises(InputError, match="expected bool"):
        write_frame_group(take, rig, full_group(take), tmp_path / "c", masks=masks)
    assert not (tmp_path / "c").exists()

    skewed = CameraRig(rig.ids, rig.K + np.array([[0, 0.5, 0], [0, 0, 0], [0, 0, 0]]), rig.dist, rig.R, rig.t,
                       rig.size)
    with pytest.raises(InputError, match="skew"):
        write_frame_group(take, skewed, full_group(take), tmp_path / "d")
    halved = CameraRig(rig.ids, rig.K, rig.dist, rig.R, rig.t, rig.size // 2)
    with pytest.raises(InputError, match="is 64x36 but its calibration is for 32x18") as err:
        write_frame_group(take, halved, full_group(take), tmp_path / "d")
    assert str(take.path) in str(err.value) and not (tmp_path / "d" / "transforms.json").exists()
    other = CameraRig(("nope",), rig.K[:1], rig.dist[:1], rig.R[:1], rig.t[:1], rig.size[:1])
    with pytest.raises(InputError, match="none of the take's cameras"):
        write_frame_group(take, other, full_group(take), tmp_path / "d")
