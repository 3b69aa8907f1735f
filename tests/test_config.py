"""rig.toml, board.toml, tags.json, subject files and model specs: every bad value is one line naming
the file, the key and the allowed range, exit code 2, before any device opens."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tomli_w
from click.testing import CliRunner

from dataset_tools.calibration.boards import load_board, load_tags
from dataset_tools.hand.bones import BONE_NAMES, BoneLengths, load_subject, save_subject
from dataset_tools.keypoints.models import load_spec
from manus_capture.cli import cli
from manus_core.errors import BoardError, BoneLengthError, ConfigError, ModelError
from manus_core.rig_config import SIM_SUBJECTS, load_rig, rig_to_dict, rig_to_toml
from manus_core.skeleton import DEFAULT_BONE_LENGTHS
from rig.layouts import make_rig
from rig.sim.hand import SUBJECTS

GOOD = """
[rig]
name = "bench"
sync = "software-trigger"

[leds]
port = "/dev/ttyACM0"

[[cameras]]
id = "left"
backend = "v4l2"
device = "/dev/v4l/by-id/usb-cam-left"

[[cameras]]
id = "right"
backend = "aravis"
device = "SN1234"
width = 1920
height = 1200
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "rig.toml"
    path.write_text(text)
    return path


def test_good_file_loads_with_defaults(tmp_path):
    rig = load_rig(write(tmp_path, GOOD))
    assert [c.id for c in rig.cameras] == ["left", "right"]
    assert rig.cameras[0].width == 1280 and rig.cameras[1].width == 1920
    assert rig.sync == "software-trigger" and rig.leds.protocol == "ascii"
    assert rig.sim is None


@pytest.mark.parametrize("edit, key, words", [
    (lambda t: t.replace('device = "SN1234"\n', ""), "cameras[1].device", "missing"),
    (lambda t: t.replace("width = 1920", 'width = "wide"'), "cameras[1].width", "must be an integer in 16..16384"),
    (lambda t: t.replace('backend = "aravis"', 'backend = "gige"'), "cameras[1].backend", "unknown backend"),
    (lambda t: t.replace('id = "right"', 'id = "left"'), "cameras[1].id", "duplicate camera id"),
    (lambda t: t.replace('sync = "software-trigger"', 'sync = "genlock"'), "sync", "is not one of"),
    (lambda t: t.replace("[leds]", "[leds]\ncolour = 3"), "leds.colour", "unknown key"),
    (lambda t: t.replace('name = "bench"', ""), "name", "missing"),
])
def test_each_error_names_file_and_key(tmp_path, edit, key, words):
    path = write(tmp_path, edit(GOOD))
    with pytest.raises(ConfigError) as err:
        load_rig(path)
    message = str(err.value)
    assert message.startswith(f"{path}: {key}: "), message
    assert words in message and "\n" not in message


def test_cli_check_reports_one_line_and_exit_2(tmp_path):
    path = write(tmp_path, GOOD.replace('id = "right"', 'id = "left"'))
    result = CliRunner().invoke(cli, ["rig", "check", str(path)])
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and "cameras[1].id: duplicate camera id 'left'" in lines[0]


# `rig init --backend v4l2 --cameras 6` as written, before the devices are filled in
V4L2_TEMPLATE = rig_to_toml(make_rig("cube53", cameras=6, resolution=(640, 360), backend="v4l2"))


def rig_key(text: str, key: str) -> str:
    """[rig] gains `key`."""
    return text.replace('name = "bench"', f'name = "bench"\n{key}')


def sim_camera(**changes) -> str:
    """A two-camera simulated rig.toml with `changes` to its first camera's [cameras.sim] table."""
    rig = make_rig("cube53", cameras=2, resolution=(64, 36))
    first = dataclasses.replace(rig.cameras[0], sim=dataclasses.replace(rig.cameras[0].sim, **changes))
    return rig_to_toml(dataclasses.replace(rig, cameras=(first, *rig.cameras[1:])))


# Each bad value of issue 22 (and its kin): the file, the key and the allowed range, in one line.
BAD_VALUES = [
    (rig_key(GOOD, "fps = -30"), "fps", "must be in (0, 10000] frames per second, got -30"),
    (rig_key(GOOD, "fps = inf"), "fps", "must be in (0, 10000] frames per second, got inf"),
    (rig_key(GOOD, "fps = nan"), "fps", "must be in (0, 10000] frames per second, got nan"),
    (rig_key(GOOD, "fps = 1e9"), "fps", "must be in (0, 10000] frames per second, got 1000000000.0"),
    (GOOD.replace("width = 1920", "width = 1000000000"), "cameras[1].width",
     "must be an integer in 16..16384 pixels, got 1000000000"),
    (GOOD.replace("width = 1920", "width = 1e9"), "cameras[1].width",
     "must be an integer in 16..16384 pixels, got 1000000000.0"),
    (GOOD.replace("height = 1200", "height = 0"), "cameras[1].height", "must be an integer in 16..16384 pixels, got 0"),
    (GOOD.replace('device = "SN1234"', 'device = "SN1234"\nfps = -1'), "cameras[1].fps",
     "must be in (0, 10000] frames per second, got -1"),
    (GOOD.replace('device = "SN1234"', 'device = "SN1234"\nexposure_us = 0'), "cameras[1].exposure_us",
     "must be in (0, 1000000] us, got 0"),
    (GOOD.replace('port = "/dev/ttyACM0"', 'port = "/dev/ttyACM0"\nlevel = 5'), "leds.level",
     "must be in [0, 1], got 5"),
    (GOOD.replace('port = "/dev/ttyACM0"', 'port = "/dev/ttyACM0"\npanels = 0'), "leds.panels",
     "must be an integer in 1..512, got 0"),
    (GOOD + "[storage]\njpeg_quality = 900\n", "storage.jpeg_quality", "must be an integer in 1..100, got 900"),
    (GOOD + "[storage]\nmin_free_gb = -5\n", "storage.min_free_gb", "must be >= 0, got -5"),
    (GOOD + "[sim]\nsupersample = -1\n", "sim.supersample", "must be an integer in 1..8, got -1"),
    (GOOD + "[sim]\ntime_scale = inf\n", "sim.time_scale", "must be in [0, 10], got inf"),
    (GOOD + '[sim]\nsubject = "s99"\n', "sim.subject",
     "unknown subject 's99' (known: s01, s02, s03, or a subject file NAME.toml)"),
    (GOOD + "[sim]\ntag_size = 0.5\n", "sim.tag_size", "0.5 m tags do not fit 5 to a 1.2 m wall (must be < 0.24 m)"),
    (sim_camera(drop_rate=2.0), "cameras[0].sim.drop_rate", "must be in [0, 1), got 2.0"),
    (sim_camera(hfov_deg=0), "cameras[0].sim.hfov_deg", "must be in (0, 180) degrees, got 0"),
    (sim_camera(drift_ppm=float("nan")), "cameras[0].sim.drift_ppm", "must be in [-1000, 1000] ppm, got nan"),
    (sim_camera(aspect=1.5), "cameras[0].sim.aspect", "must be in [0.9, 1.1], got 1.5"),
    (sim_camera(aspect=0), "cameras[0].sim.aspect", "must be in [0.9, 1.1], got 0"),
    (sim_camera(principal_offset=(0.5, 0.0)), "cameras[0].sim.principal_offset[0]",
     "must be in [-0.1, 0.1] of the image's side, got 0.5"),
    (sim_camera(principal_offset=(0.0, float("inf"))), "cameras[0].sim.principal_offset[1]",
     "must be in [-0.1, 0.1] of the image's side, got inf"),
    (sim_camera(principal_offset=(0.01,)), "cameras[0].sim.principal_offset[1]", "missing"),
    (sim_camera(latency_ms=-2), "cameras[0].sim.latency_ms", "must be in [0, 1000] ms, got -2"),
    (sim_camera(look_at=(0.55, 0.0, 0.0)), "cameras[0].sim.look_at",
     "must differ from the camera's position, got [0.55, 0.0, 0.0]"),
    (sim_camera(up=(-0.55, 0.0, -0.05)), "cameras[0].sim.up",
     "must be neither zero nor along the viewing direction, got [-0.55, 0.0, -0.05]"),
    (sim_camera(up=(0.0, 0.0, 0.0)), "cameras[0].sim.up", "must be neither zero nor along the viewing direction"),
    (GOOD.replace('id = "right"', 'id = "left"'), "cameras[1].id", "duplicate camera id 'left' (also cameras[0])"),
    (GOOD.replace('device = "SN1234"', 'device = ""'), "cameras[1].device", "must not be empty"),
    (GOOD.replace('backend = "aravis"', 'backend = "v4l2"').replace('"SN1234"', '"/dev/v4l/by-id/usb-cam-left"'),
     "cameras[1].device", "'/dev/v4l/by-id/usb-cam-left' is also the device of cameras[0]; each camera needs its own"),
    (V4L2_TEMPLATE, "cameras[0].device", "'/dev/v4l/by-id/CHANGE-ME' is a placeholder: give the camera's serial number"),
]


@pytest.mark.faults
@pytest.mark.parametrize("text, key, words", BAD_VALUES, ids=[f"{k}={w[:24]}" for _, k, w in BAD_VALUES])
def test_cli_check_rejects_values_out_of_range(tmp_path, text, key, words):
    path = write(tmp_path, text)
    result = CliRunner().invoke(cli, ["rig", "check", str(path)])
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and f"{path}: {key}: {words}" in lines[0], result.output
    assert "ok" not in lines


@pytest.mark.faults
@pytest.mark.parametrize("command", ["check", "record"])
def test_bad_rig_fails_before_any_device_opens(tmp_path, command):
    """The real command line: the six V4L2 cameras of `rig init` still at CHANGE-ME (rig check), a
    drop rate of 2 (record, which once hung with a traceback and a take left `recording`)."""
    path = tmp_path / "rig.toml"
    if command == "check":
        made = CliRunner().invoke(cli, ["rig", "init", "--backend", "v4l2", "--cameras", "6", "-o", str(path)])
        assert made.exit_code == 0 and "each camera's device is CHANGE-ME" in made.output, made.output
    else:
        write(tmp_path, sim_camera(drop_rate=2.0))
    args = ["rig", "check", str(path)] if command == "check" else [
        "record", "--rig", str(path), "--session", str(tmp_path / "S"), "--take", "t", "--kind", "grasp",
        "--duration", "1"]
    done = subprocess.run([sys.executable, "-m", "manus_capture.cli", *args], capture_output=True, text=True,
                          timeout=60)
    key = "cameras[0].device" if command == "check" else "cameras[0].sim.drop_rate"
    assert done.returncode == 2 and done.stdout == "", done.stdout + done.stderr
    assert done.stderr.splitlines() == [done.stderr.strip()] and f"{path}: {key}: " in done.stderr, done.stderr
    assert not (tmp_path / "S").exists()


def test_the_simulated_subjects_are_the_ones_rig_toml_allows():
    assert SIM_SUBJECTS == tuple(SUBJECTS)


def test_cli_check_summary(tmp_path):
    result = CliRunner().invoke(cli, ["rig", "check", str(write(tmp_path, GOOD))])
    assert result.exit_code == 0, result.output
    assert "1 aravis, 1 v4l2" in result.output and "software-trigger" in result.output


def test_missing_and_broken_files(tmp_path):
    with pytest.raises(ConfigError, match="no such file"):
        load_rig(tmp_path / "nope.toml")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_rig(write(tmp_path, "[rig\nname="))


def test_generated_rig_round_trips(tmp_path):
    rig = make_rig("cube53", cameras=12, resolution=(320, 180), seed=3)
    again = load_rig(write(tmp_path, rig_to_toml(rig)))
    assert again.cameras == rig.cameras and again.sim == rig.sim and again.leds == rig.leds


def test_rig_init_cube53(tmp_path):
    out = tmp_path / "rig.toml"
    result = CliRunner().invoke(cli, ["rig", "init", "--layout", "cube53", "-o", str(out)])
    assert result.exit_code == 0, result.output
    rig = load_rig(out)
    assert len(rig.cameras) == 53 and rig.fps == 120
    assert {(c.width, c.height) for c in rig.cameras} == {(1280, 720)}
    faces = {c.id[:2] for c in rig.cameras}
    assert faces == {"x+", "x-", "y+", "y-", "z+", "z-"}
    assert sum(c.id.startswith("z-") for c in rig.cameras) == 8  # the table takes the floor's centre
    # realistic, non-zero imperfections by default
    offsets = [abs(c.sim.clock_offset_ms) for c in rig.cameras]
    drifts = [abs(c.sim.drift_ppm) for c in rig.cameras]
    assert 0.5 < sum(offsets) / 53 < 5 and 5 < sum(drifts) / 53 < 60
    assert all(0 < c.sim.drop_rate < 0.05 for c in rig.cameras)
    again = CliRunner().invoke(cli, ["rig", "init", "-o", str(out)])
    assert again.exit_code != 0 and "--force" in again.output


def test_rig_init_subset_spreads_over_faces(tmp_path):
    out = tmp_path / "rig.toml"
    result = CliRunner().invoke(cli, ["rig", "init", "--cameras", "12", "--resolution", "320x180",
                                      "--fps", "60", "-o", str(out)])
    assert result.exit_code == 0, result.output
    rig = load_rig(out)
    assert len(rig.cameras) == 12 and len({c.id[:2] for c in rig.cameras}) == 6
    assert rig.cameras[0].width == 320 and rig.fps == 60


def test_help_lists_every_design_command():
    out = subprocess.run([sys.executable, "-m", "manus_capture.cli", "--help"], capture_output=True,
                         text=True, check=True).stdout
    for name in ["rig", "leds", "record", "protocol", "sync-report", "calibrate", "models", "detect",
                 "annotate", "stats", "segment", "reconstruct", "contacts", "evaluate", "demo"]:
        assert f"  {name} " in out
    version = subprocess.run([sys.executable, "-m", "manus_capture.cli", "--version"], capture_output=True,
                             text=True, check=True).stdout
    assert "manus-capture, version" in version


# -- the other configuration files: board.toml, tags.json, subject files, model specs --------------

BOARD = 'type = "charuco"\ncols = 4\nrows = 5\nsquare = 0.054\nmarker = 0.04\ndictionary = "DICT_4X4_1000"\n'


@pytest.mark.faults
@pytest.mark.parametrize("text, words", [
    (BOARD.replace("cols = 4", "cols = 1000"), "key 'cols' must be an integer >= 2 and <= 100, got 1000"),
    (BOARD.replace("rows = 5", "rows = 1"), "key 'rows' must be an integer >= 2 and <= 100, got 1"),
    (BOARD.replace("square = 0.054", "square = 1e-6"), "key 'square' must be a length in metres >= 0.001 (1 mm), got 1e-06"),
    (BOARD.replace("square = 0.054", "square = nan"), "key 'square' must be a length in metres >= 0.001 (1 mm), got nan"),
    (BOARD.replace("marker = 0.04", "marker = inf"), "key 'marker' must be a length in metres >= 0, got inf"),
])
def test_board_values_out_of_range(tmp_path, text, words):
    path = tmp_path / "board.toml"
    path.write_text(text)
    with pytest.raises(BoardError) as err:
        load_board(path)
    assert str(err.value) == f"{path}: {words}"


CORNERS = [[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0], [0, 0.1, 0]]


@pytest.mark.faults
@pytest.mark.parametrize("tags, words", [
    ('{"600": C}', "key 'tags.600' is not a tag of tag36h11 (ids 0..586)"),
    ('{"-1": C}', "key 'tags.-1' is not a tag of tag36h11 (ids 0..586)"),
    ('{"03": C, "3": C}', "key 'tags.3' is tag 3 again"),
    ('{"3": C, "3": C}', "key '3' is given twice"),
])
def test_tag_ids_are_tags_of_the_family_and_unique(tmp_path, tags, words):
    path = tmp_path / "tags.json"
    path.write_text('{"family": "tag36h11", "size": 0.1, "tags": ' + tags.replace("C", json.dumps(CORNERS)) + "}")
    with pytest.raises(BoardError) as err:
        load_tags(path)
    assert str(err.value) == f"{path}: {words}"


def subject_doc(tmp_path: Path) -> dict:
    bones = BoneLengths(DEFAULT_BONE_LENGTHS, np.full(20, 1e-4), np.full(20, 30))
    return json.loads(save_subject(tmp_path / "s01.json", "s01", bones).read_text())


LENGTHS = "bone_lengths: must be 20 positive lengths in metres, each in [0.005, 0.15], got "


@pytest.mark.faults
@pytest.mark.parametrize("change, words", [
    ({"bone_lengths": [45.0] + [0.03] * 19}, LENGTHS + "[45.0, 0.03"),     # millimetres
    ({"bone_lengths": [-0.03] * 20}, LENGTHS + "[-0.03"),
    ({"bone_lengths": [0.0] * 20}, LENGTHS + "[0.0"),
    ({"bone_lengths": [float("nan")] * 20}, LENGTHS + "[nan"),
    ({"bone_lengths": [0.03] * 19}, LENGTHS + "[0.03"),
    ({"units": "mm"}, "units: is 'mm'; the lengths must be in metres ('m')"),
    ({"bone_names": list(BONE_NAMES[::-1])}, "bone_names: must list the 20 bones in the order wrist-thumb_cmc ... "
                                             "pinky_dip-pinky_tip, got ['pinky_dip-pinky_tip'"),
    ({"spread_m": [-1.0] * 20}, "spread_m[0]: must be >= 0, got -1.0"),
])
def test_subject_file_values(tmp_path, change, words):
    path = tmp_path / "s01.json"
    path.write_text(json.dumps({**subject_doc(tmp_path), **change}))
    with pytest.raises(BoneLengthError) as err:
        load_subject(path)
    assert str(err.value).startswith(f"{path}: {words}"), err.value
    assert err.value.exit_code == 2


SPEC = ('kind = "simcc"\nmodel = "m.onnx"\ninput_size = [192, 256]\nmean = [0.0, 0.0, 0.0]\nstd = [1.0, 1.0, 1.0]\n'
        'box_scale = 1.25\nkeypoints = [' + ", ".join(map(str, range(21))) + ']\n[simcc]\nsplit_ratio = 2.0\n')


@pytest.mark.faults
@pytest.mark.parametrize("text, words", [
    (SPEC.replace("[192, 256]", "[0, 256]"), "input_size: expected [width, height] in pixels, each in 16..4096, "
                                             "got [0, 256]"),
    (SPEC.replace("[192, 256]", "[192, 1000000]"), "input_size: expected [width, height] in pixels, each in 16..4096"),
    (SPEC.replace("box_scale = 1.25", "box_scale = 0"), "box_scale: must be in [1, 4], got 0"),
    (SPEC.replace("box_scale = 1.25", "box_scale = inf"), "box_scale: must be in [1, 4], got inf"),
    (SPEC.replace("box_scale = 1.25", "box_scal = 1.25"), "box_scal: unknown key (known: box_scale, color, "),
    (SPEC.replace("mean = [0.0", "mean = [nan"), "mean[0]: expected a finite number, got nan"),
    (SPEC.replace("std = [1.0", "std = [0.0"), "std[0]: must be > 0, got 0.0"),
    (SPEC.replace("split_ratio = 2.0", "split_ratio = -2.0"),
     "simcc.split_ratio: must be in (0, 16] bins per input pixel, got -2.0"),
    (SPEC.replace("[0, 1, 2, 3, 4, 5, 6,", "[0, 1, 2, 3, 4, 6, 6,"),
     "keypoints: model joint 6 is given for index1 and index2; each model joint is one MediaPipe joint"),
    (SPEC.replace("keypoints = [0, 1", "keypoints = [-1, -1").split("keypoints")[0] + "keypoints = [" +
     ", ".join(["-1"] * 21) + "]\n", "keypoints: no joint is given (all -1)"),
])
def test_model_spec_values(tmp_path, text, words):
    path = tmp_path / "spec.toml"
    path.write_text(text)
    with pytest.raises(ModelError) as err:
        load_spec(path)
    assert str(err.value).startswith(f"{path}: {words}"), err.value
    assert err.value.exit_code == 2


def test_sim_optics_default_to_a_centred_square_pixel_camera(tmp_path):
    """A rig.toml written before the sim cameras had principal_offset and aspect keeps meaning what
    it meant: the principal point at the image centre, fx == fy."""
    from rig.sim.cube import true_cameras

    doc = rig_to_dict(make_rig("cube53", cameras=2, resolution=(64, 36)))
    for cam in doc["cameras"]:
        del cam["sim"]["principal_offset"], cam["sim"]["aspect"]
    rig = load_rig(write(tmp_path, tomli_w.dumps(doc)))
    assert all(c.sim.aspect == 1.0 and c.sim.principal_offset == (0.0, 0.0) for c in rig.cameras)
    K = true_cameras(rig).K
    np.testing.assert_array_equal(K[:, 0, 0], K[:, 1, 1])
    np.testing.assert_array_equal(K[:, :2, 2], [[31.5, 17.5], [31.5, 17.5]])
