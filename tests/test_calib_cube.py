"""The full simulated cube (53 cameras, 640x360) calibrated from its wall tags, against the true cameras.

cube53 aims the four floor cameras beside the table (z-01, z-10, z-12, z-21) up over it, as a lab
would: every camera sees two tags or more and the tag method alone must place all 53. The second
test aims those four at the cube's centre instead, into the table's side, where they see one tag
or none: they are placed from scene features that the tag-calibrated cameras triangulate
(features.py), to millimetres.
Then a calibration take of 12 cameras is recorded (JPEG, sensor noise) and calibrated end to end by
`manus-capture calibrate rig`; its cameras.json is scored against ground_truth.h5 and every export
read back.
"""

from __future__ import annotations

import dataclasses
import json
import tomllib

import numpy as np
import pytest
import tomli_w

from dataset_tools.calibration.boards import tags_from_dict
from dataset_tools.calibration.formats import load_cameras
from dataset_tools.calibration.rig import calibrate_rig
from manus_core.ground_truth import GroundTruth
from manus_core.rotations import rotation_angle_deg
from rig.layouts import make_rig
from rig.sim.cube import true_cameras
from rig.sim.render import Renderer
from rig.sim.world import World

INTO_THE_TABLE = ("z-01", "z-10", "z-12", "z-21")


def _aimed_at(config, z: float):
    cams = tuple(dataclasses.replace(c, sim=dataclasses.replace(c.sim, look_at=(0.0, 0.0, z)))
                 if c.id in INTO_THE_TABLE else c for c in config.cameras)
    return dataclasses.replace(config, cameras=cams)


def _render(truth, ids):
    # supersample 1: the walls are mip-mapped, so one ray per pixel already integrates the texture
    renderer = Renderer(World(), truth, supersample=1)
    return {c: [(renderer.background(truth.index(c))[0] * 255).round().astype(np.uint8)] for c in ids}


@pytest.fixture(scope="module")
def cube():
    config = make_rig(resolution=(640, 360), seed=1)
    stock, into = true_cameras(config), true_cameras(_aimed_at(config, -0.05))
    images = _render(stock, stock.ids)
    into_table = _render(into, INTO_THE_TABLE)
    layout = tags_from_dict(World().tags_json())
    return stock, into, images, into_table, layout


def errors(result, truth):
    est, ref = result.rig, truth.subset(result.rig.ids)
    centre_mm = np.linalg.norm(est.centers - ref.centers, axis=1) * 1000
    return dict(zip(est.ids, centre_mm)), dict(zip(est.ids, rotation_angle_deg(est.R, ref.R)))


def test_53_camera_poses_from_tags_given_the_true_intrinsics(cube):
    truth, _, images, _, layout = cube
    assert len(truth) == 53
    result = calibrate_rig(images, tags=layout, intrinsics=truth, method="tags", workers=1)
    assert not result.partial and sorted(result.rig.ids) == sorted(truth.ids)
    assert "scene_points" not in result.extra  # every camera placed by its own tags
    centre_mm, rot_deg = errors(result, truth)
    assert max(centre_mm.values()) < 2.0, {c: round(e, 2) for c, e in centre_mm.items() if e > 1}
    assert max(rot_deg.values()) < 0.1
    assert result.median_px < 0.3
    assert abs(result.extra["checks"]["scale"]["error_pct"]) < 0.1


def test_cameras_without_tags_placed_from_the_scene_given_the_true_intrinsics(cube):
    _, truth, images, into_table, layout = cube
    views = {**images, **into_table}
    result = calibrate_rig(views, tags=layout, intrinsics=truth, method="tags", workers=1)
    assert not result.partial and len(result.rig) == 53
    scene = sorted(result.extra["scene_points"])
    # z-10 and z-12 see no tag; z-01 sees one whole tag; z-21's wider lens (k1 -0.22) takes in three
    assert {"z-10", "z-12", "z-01"} <= set(scene) <= set(INTO_THE_TABLE), scene
    assert all(v["points"] >= 30 for v in result.extra["scene_points"].values())
    centre_mm, rot_deg = errors(result, truth)
    # z-01 sees one whole tag and z-21 three: its corners, weighted by their precision, with the
    # scene's points hold them within the bounds of the tag cameras
    assert max(centre_mm["z-01"], centre_mm["z-21"]) < 2.0, {c: round(centre_mm[c], 2) for c in INTO_THE_TABLE}
    assert max(rot_deg["z-01"], rot_deg["z-21"]) < 0.1
    # z-10 and z-12 see no tag: scene points alone, millimetres. 4.9 and 12.4 mm measured since the
    # sim's lenses vary (issue 19; 6.5 and 4.5 mm with centred, nearly undistorted lenses): z-10 now
    # matches 69 points over 13 % of its image. COLMAP put one of them 22 mm off.
    assert max(centre_mm[c] for c in INTO_THE_TABLE) < 15.0, {c: round(centre_mm[c], 2) for c in INTO_THE_TABLE}
    assert max(rot_deg[c] for c in INTO_THE_TABLE) < 0.6   # 0.55 deg measured on z-10
    # and the cameras placed by tags are not disturbed by them
    assert max(e for c, e in centre_mm.items() if c not in INTO_THE_TABLE) < 2.0


# --- intrinsics from the tags (issue 19) -----------------------------------------------------------

@pytest.fixture(scope="module")
def dense_cube():
    """The cube at 640x360 tagged as a lab would for calibrating intrinsics too (8 x 8 tags of 9 cm
    a wall and the table's sides, docs/calibration.md), rendered through the sim's true cameras,
    whose intrinsics differ camera by camera from any nominal value."""
    world = World(tags_per_wall=8, tag_size=0.09, table_tags=True)
    truth = true_cameras(make_rig(resolution=(640, 360), seed=1))
    renderer = Renderer(world, truth, supersample=1)
    images = {c: [(renderer.background(truth.index(c))[0] * 255).round().astype(np.uint8)] for c in truth.ids}
    return truth, images, tags_from_dict(world.tags_json())


def test_53_cameras_intrinsics_and_poses_from_the_tags_alone(dense_cube):
    """No intrinsics file, no board: every camera's K, distortion and pose from the tags it sees.
    Every camera meets the issue's bounds, the floor cameras beside the table too (measured max:
    fx 0.037 %, fy 0.039 %, principal point 0.67 px, centre 0.89 mm, rotation 0.078 deg,
    reprojection in the volume 0.17 px median; z+01 named weak)."""
    truth, images, layout = dense_cube
    spread = truth.K[:, 0, 0] / truth.size[:, 0]
    assert spread.max() / spread.min() > 1.03 and np.abs(truth.dist[:, 0]).max() > 0.2   # not a nominal rig
    assert np.abs(truth.K[:, :2, 2] - (truth.size - 1) / 2).max() > 5
    result = calibrate_rig(images, tags=layout, method="tags", workers=1)
    assert not result.partial and sorted(result.rig.ids) == sorted(truth.ids)
    est, ref = result.rig, truth.subset(result.rig.ids)
    info = result.extra["intrinsics"]
    weak = sorted(c for c, e in info.items() if e["weak"])
    # a camera whose tags lie on one wall gets the others' median focal length, and is named
    assert set(info) == set(est.ids) and all(info[c]["model"] or c in weak for c in est.ids)
    assert len(weak) <= 2, weak
    fx = np.abs(est.K[:, 0, 0] / ref.K[:, 0, 0] - 1)
    fy = np.abs(est.K[:, 1, 1] / ref.K[:, 1, 1] - 1)
    pp = np.abs(est.K[:, :2, 2] - ref.K[:, :2, 2]).max(axis=1)
    centre_mm = np.linalg.norm(est.centers - ref.centers, axis=1) * 1000
    rot = rotation_angle_deg(est.R, ref.R)
    X = np.random.default_rng(0).uniform(-0.3, 0.3, (2000, 3))     # the capture volume
    seen = ref.project(X)
    inside = (seen >= 0).all(-1) & (seen < ref.size[:, None]).all(-1)
    reproj = np.where(inside, np.linalg.norm(est.project(X) - seen, axis=-1), np.nan)
    reproj = np.nanmedian(reproj, axis=1)
    bad = {c: dict(fx_pct=round(100 * fx[i], 3), fy_pct=round(100 * fy[i], 3), pp_px=round(pp[i], 2),
                   centre_mm=round(centre_mm[i], 2), rot_deg=round(rot[i], 3), reproj_px=round(reproj[i], 3))
           for i, c in enumerate(est.ids) if not (
               fx[i] < 0.003 and fy[i] < 0.003 and pp[i] < 1.0 and centre_mm[i] < 2.0 and rot[i] < 0.1
               and reproj[i] < 0.3)}
    assert not bad, bad
    assert abs(result.extra["checks"]["scale"]["error_pct"]) < 0.1
    layout_check = result.extra["checks"]["layout"]
    assert not layout_check["disagreeing"] and layout_check["tags_checked"] > 300
    assert layout_check["median_mm"] < 0.2   # measured 0.07 mm


def test_tags_that_disagree_with_tags_json_are_named_and_left_out(dense_cube, tmp_path):
    """tags.json with one tag 2 cm off, one listed mirrored and one listed 4 % small (as if printed
    at another size; tags.json's own check lets 5 % through): each is named with what is wrong in
    report.json and report.md, and left out, so the cameras meet the same bounds as before."""
    truth, images, layout = dense_cube
    corners = layout.corners.copy()
    moved, mirrored, small = (int(np.flatnonzero(layout.ids == t)[0]) for t in (40, 100, 200))
    corners[moved] += 0.02 * (corners[moved][1] - corners[moved][0]) / layout.size   # 2 cm along its row
    corners[mirrored] = corners[mirrored][[1, 0, 3, 2]]
    corners[small] = corners[small].mean(0) + 0.96 * (corners[small] - corners[small].mean(0))
    wrong = dataclasses.replace(layout, corners=corners)
    result = calibrate_rig(images, tags=wrong, method="tags", workers=1, output=tmp_path / "cal")
    named = json.loads((tmp_path / "cal" / "report.json").read_text())["checks"]["layout"]["disagreeing"]
    assert sorted(named) == ["100", "200", "40"], named
    assert "20.0 mm from where tags.json puts it" in named["40"]
    assert named["100"] == "mirrored left to right in tags.json"
    assert "its side is 90.0 mm, tags.json gives 86.4 mm" in named["200"]
    assert "tag 40 disagrees with tags.json and was left out" in (tmp_path / "cal" / "report.md").read_text()
    est, ref = result.rig, truth.subset(result.rig.ids)
    assert len(est) == len(truth)
    assert (np.linalg.norm(est.centers - ref.centers, axis=1) * 1000).max() < 2.0
    assert np.abs(est.K[:, 0, 0] / ref.K[:, 0, 0] - 1).max() < 0.003


# --- a recorded take, through the command line ---------------------------------------------------

def _ground_truth(take_dir):
    cams = GroundTruth.of_take(take_dir).cameras
    return cams.ids, cams.K, cams.dist, cams.R, cams.t


# the centre of each wall, two top and two bottom corners of the cube: each sees two whole tags or more
RECORDED = ("x+11", "x-11", "y+11", "y-11", "x+02", "x-22", "y+20", "y-02", "z+00", "z+22", "z-00", "z-22")


def recording_rig():
    config = make_rig(resolution=(480, 270), seed=2)
    return dataclasses.replace(config, cameras=tuple(c for c in config.cameras if c.id in RECORDED))


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """12 cameras of the cube, 480x270, a few frames of the calibration take (JPEG, sensor noise),
    calibrated by `manus-capture calibrate rig` with the true intrinsics (no poses) as --intrinsics."""
    from click.testing import CliRunner

    from manus_capture.cli import cli
    from manus_core.cameras import CameraRig
    from rig.record import record_take

    root = tmp_path_factory.mktemp("calib-take")
    config = recording_rig()
    record_take(config, root / "session", "calib", "calibration", 0.05)
    take = root / "session" / "calib"
    ids, K, dist, R, t = _ground_truth(take)
    CameraRig(ids, K, dist, np.tile(np.eye(3), (len(ids), 1, 1)), np.zeros((len(ids), 3)),
              [[480, 270]] * len(ids)).save(root / "intrinsics.json")
    out = root / "calib-out"
    res = CliRunner().invoke(cli, ["calibrate", "rig", str(take), "--tags", str(root / "session" / "tags.json"),
                                   "--intrinsics", str(root / "intrinsics.json"), "--workers", "1", "-o", str(out)])
    return res, out, CameraRig(ids, K, dist, R, t, [[480, 270]] * len(ids))


def test_calibrate_rig_command_with_the_true_intrinsics_as_a_file(recorded):
    res, out, truth = recorded
    assert res.exit_code == 0, res.output
    assert "wrote" in res.output and "12 cameras" in res.output and "complete" in res.output
    est = load_cameras(out / "cameras.json")
    ref = truth.subset(est.ids)
    assert sorted(est.ids) == sorted(truth.ids)
    centre_mm = np.linalg.norm(est.centers - ref.centers, axis=1) * 1000
    # JPEG and sensor noise at 480x270: every camera within the 53-camera test's own bounds
    assert centre_mm.max() < 2.0, dict(zip(est.ids, centre_mm.round(2)))
    assert rotation_angle_deg(est.R, ref.R).max() < 0.1
    report = json.loads((out / "report.json").read_text())
    assert report["partial"] is False and len(report["cameras"]) == 12
    assert (out / "report.md").stat().st_size > 0 and (out / "cameras.png").stat().st_size > 0


@pytest.mark.parametrize("export", ["colmap", "cameras.yml", "easymocap", "optim_params.txt"])
def test_every_export_of_the_take_round_trips(recorded, export):
    res, out, _ = recorded
    assert res.exit_code == 0, res.output
    ref = load_cameras(out / "cameras.json")
    back = load_cameras(out / export).subset(ref.ids)
    X = np.random.default_rng(0).uniform(-0.4, 0.4, (50, 3))
    assert np.nanmax(np.abs(back.project(X) - ref.project(X))) < 1e-3


@pytest.fixture(scope="module")
def recorded_alone(tmp_path_factory):
    """The 12 cameras' calibration take again, on walls tagged 8 x 8, calibrated by `manus-capture
    calibrate rig TAKE -o CAL` and nothing else, from a copy of the take without ground_truth.h5
    and a session.toml without any [sim] table: the calibration cannot read the truth."""
    from click.testing import CliRunner

    from manus_capture.cli import cli
    from manus_core.cameras import CameraRig
    from rig.record import record_take

    root = tmp_path_factory.mktemp("calib-alone")
    config = recording_rig()
    config = dataclasses.replace(config, sim=dataclasses.replace(config.sim, tags_per_wall=8, tag_size=0.09))
    record_take(config, root / "session", "calib", "calibration", 0.05)
    take = root / "session" / "calib"
    truth = CameraRig(*_ground_truth(take), [[480, 270]] * len(config.cameras))
    (take / "ground_truth.h5").unlink()
    doc = tomllib.loads((root / "session" / "session.toml").read_text())
    doc.pop("sim", None)
    for cam in doc.get("cameras", []):
        cam.pop("sim", None)
    (root / "session" / "session.toml").write_text(tomli_w.dumps(doc))
    out = root / "cal"
    res = CliRunner().invoke(cli, ["calibrate", "rig", str(take), "--workers", "1", "-o", str(out)])
    return res, out, truth


def test_calibrate_rig_needs_nothing_but_the_take(recorded_alone):
    res, out, truth = recorded_alone
    assert res.exit_code == 0, res.output
    assert "12 cameras" in res.stdout and "intrinsics from the tags: 12 cameras" in res.stdout
    est = load_cameras(out / "cameras.json")
    ref = truth.subset(est.ids)
    report = json.loads((out / "report.json").read_text())
    weak = sorted(c for c, e in report["details"]["intrinsics"].items() if e["weak"])
    assert all(f"warning: camera {c}: weakly constrained" in res.stderr for c in weak)
    keep = [i for i, c in enumerate(est.ids) if c not in weak]
    assert len(keep) >= 10, weak
    fx = np.abs(est.K[keep, 0, 0] / ref.K[keep, 0, 0] - 1)
    centre_mm = np.linalg.norm(est.centers[keep] - ref.centers[keep], axis=1) * 1000
    assert fx.max() < 0.003 and centre_mm.max() < 2.0, (fx.round(4), centre_mm.round(2))
    assert np.abs(est.K[keep, :2, 2] - ref.K[keep, :2, 2]).max() < 1.0
    assert rotation_angle_deg(est.R[keep], ref.R[keep]).max() < 0.1
    assert "Intrinsics estimated from the tags" in (out / "report.md").read_text()



def test_calibrate_rig_names_what_it_cannot_do(recorded_alone, tmp_path):
    """Without tags.json anywhere it looks: one line naming where it looked and --tags, exit 2. A
    camera that sees no tag and shares no scene features with the others (a grey picture, as with
    its lens cap on): named, exit 1; with --allow-partial the others are calibrated and it is left out."""
    import subprocess

    from click.testing import CliRunner

    from manus_capture.cli import cli

    _, out, _ = recorded_alone
    cams = out.parent / "session" / "calib" / "cams"
    videos = tmp_path / "videos"
    videos.mkdir()
    for cam in ("x+11", "y+11", "x-11", "y-11", "z+00"):
        (videos / f"{cam}.mkv").symlink_to(cams / f"{cam}.mkv")
    subprocess.run(["ffmpeg", "-v", "error", "-f", "lavfi", "-i", "color=c=gray:s=480x270:r=120", "-frames:v", "6",
                    "-c:v", "mjpeg", str(videos / "capped.mkv")], check=True)
    res = CliRunner().invoke(cli, ["calibrate", "rig", str(videos), "--workers", "1", "-o", str(tmp_path / "a")])
    assert res.exit_code == 2 and "no tags.json in" in res.output and "--tags FILE" in res.output, res.output
    tags = out.parent / "session" / "tags.json"
    args = ["calibrate", "rig", str(videos), "--tags", str(tags), "--workers", "1"]
    res = CliRunner().invoke(cli, [*args, "-o", str(tmp_path / "b")])
    assert res.exit_code == 1 and "camera capped: sees no tag of" in res.output, res.output
    assert "--allow-partial" in res.output and not (tmp_path / "b" / "cameras.json").exists()
    res = CliRunner().invoke(cli, [*args, "--allow-partial", "-o", str(tmp_path / "c")])
    assert res.exit_code == 0 and "left out: camera capped: sees no tag of" in res.output, res.output
    assert sorted(load_cameras(tmp_path / "c" / "cameras.json").ids) == ["x+11", "x-11", "y+11", "y-11", "z+00"]
