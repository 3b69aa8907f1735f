"""rig.toml: validation errors name the file and the key, in one line, with exit code 2."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from manus_capture.cli import cli
from manus_core.errors import ConfigError
from manus_core.rig_config import load_rig, rig_to_toml
from rig.layouts import make_rig

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
    (lambda t: t.replace("width = 1920", 'width = "wide"'), "cameras[1].width", "expected an integer"),
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


SIM_RIG = rig_to_toml(make_rig("cube53", cameras=2, resolution=(64, 36)))


@pytest.mark.parametrize("text, key, words", [
    (GOOD.replace('name = "bench"', 'name = "bench"\nfps = -30'), "fps", "must be > 0, got -30"),
    (GOOD.replace('name = "bench"', 'name = "bench"\nfps = inf'), "fps", "expected a finite number, got inf"),
    (GOOD.replace('name = "bench"', 'name = "bench"\nfps = nan'), "fps", "expected a finite number, got nan"),
    (GOOD.replace("width = 1920", "width = 1000000000"), "cameras[1].width", "must be <= 16384"),
    (GOOD.replace('port = "/dev/ttyACM0"', 'port = "/dev/ttyACM0"\nlevel = 5'), "leds.level", "must be in [0, 1]"),
    (GOOD + "[storage]\njpeg_quality = 900\n", "storage.jpeg_quality", "must be an integer in 1..100"),
    (GOOD + "[storage]\nmin_free_gb = -5\n", "storage.min_free_gb", "must be >= 0"),
    (GOOD + "[sim]\nsupersample = -1\n", "sim.supersample", "must be >= 1"),
    (SIM_RIG.replace("drop_rate = 0.002", "drop_rate = 2.0", 1), "cameras[0].sim.drop_rate", "must be in [0, 1)"),
    (re.sub(r"hfov_deg = [\d.]+", "hfov_deg = 0", SIM_RIG, count=1), "cameras[0].sim.hfov_deg", "must be in (0, 180)"),
])
def test_cli_check_rejects_values_out_of_range(tmp_path, text, key, words):
    path = write(tmp_path, text)
    result = CliRunner().invoke(cli, ["rig", "check", str(path)])
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and f"{path}: {key}: {words}" in lines[0], result.output


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
