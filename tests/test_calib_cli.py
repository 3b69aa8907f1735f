"""`manus-capture calibrate`: both commands end to end on real data, and their errors."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from dataset_tools.calibration.formats import load_cameras
from manus_capture.cli import cli

CHARUCO_TOML = ('type = "charuco"\ncols = 4\nrows = 5\nsquare = 0.054\nmarker = 0.0405\n'
                'dictionary = "DICT_4X4_1000"\ninverted = true\n')


def test_intrinsics_command(shared_data, tmp_path):
    board = tmp_path / "board.toml"
    board.write_text('type = "chessboard"\ncols = 9\nrows = 6\nsquare = 0.025\n')
    images = sorted(str(p) for p in (shared_data / "opencv_stereo_chessboard").glob("left0*.jpg"))[:6]
    out = tmp_path / "left.json"
    res = CliRunner().invoke(cli, ["calibrate", "intrinsics", *images, "--board", str(board), "-o", str(out),
                                   "--camera-id", "left"])
    assert res.exit_code == 0, res.output
    assert "wrote" in res.output and "RMS" in res.output
    rig = load_cameras(out)
    assert rig.ids == ("left",) and tuple(rig.size[0]) == (640, 480)
    assert rig.K[0, 0, 0] == pytest.approx(535.9, rel=0.01) and rig.rms_px[0] < 0.3
    again = CliRunner().invoke(cli, ["calibrate", "intrinsics", *images, "--board", str(board), "-o", str(out)])
    assert again.exit_code == 2 and "exists" in again.output


def test_intrinsics_command_bad_board_is_one_line(shared_data, tmp_path):
    board = tmp_path / "board.toml"
    board.write_text('type = "chessboard"\ncols = 10\nrows = 7\nsquare = 0.025\n')  # squares, not corners
    images = sorted(str(p) for p in (shared_data / "opencv_stereo_chessboard").glob("left0*.jpg"))[:3]
    res = CliRunner().invoke(cli, ["calibrate", "intrinsics", *images, "--board", str(board), "-o",
                                   str(tmp_path / "x.json")])
    assert res.exit_code == 2
    line = res.output.strip().splitlines()[-1]
    assert "no board in 3 frames" in line and "cols = 9, rows = 6" in line and "Traceback" not in res.output


def test_rig_command_on_a_folder_of_videos(shared_data, tmp_path):
    videos = tmp_path / "session"
    videos.mkdir()
    for c in range(4):
        (videos / f"cam{c}.mp4").symlink_to(shared_data / f"caliscope_4cam_charuco/calibration/extrinsic/cam_{c}.mp4")
    board = tmp_path / "board.toml"
    board.write_text(CHARUCO_TOML)
    out = tmp_path / "calib"
    res = CliRunner().invoke(cli, ["calibrate", "rig", str(videos), "--board", str(board), "--board-frames", "20",
                                   "--workers", "1", "-o", str(out)])
    assert res.exit_code == 0, res.output
    assert "4 cameras (board)" in res.output and "complete" in res.output
    rig = load_cameras(out / "cameras.json")
    assert rig.ids == ("cam0", "cam1", "cam2", "cam3")
    report = json.loads((out / "report.json").read_text())
    assert not report["partial"] and abs(report["checks"]["scale"]["error_pct"]) < 2
    assert set(report["cameras"]) == set(rig.ids) and report["rms_px"] < 2
    for name in ("report.md", "cameras.png", "cameras.yml", "optim_params.txt", "colmap/cameras.txt",
                 "easymocap/intri.yml"):
        assert (out / name).stat().st_size > 0, name
    # every export reads back as the same cameras
    for export in ("colmap", "cameras.yml", "easymocap"):
        back = load_cameras(out / export)
        assert back.ids == rig.ids
        assert abs(back.project(rig.centers[:1] * 0 + [[0.1, 0.1, 0.0]]) - rig.project([[0.1, 0.1, 0.0]])).max() < 1e-3
    again = CliRunner().invoke(cli, ["calibrate", "rig", str(videos), "--board", str(board), "-o", str(out)])
    assert again.exit_code == 2 and "pass --force" in again.output


@pytest.mark.faults
def test_rig_command_leaves_out_an_unreadable_video(shared_data, tmp_path):
    """One camera's video is garbage: --allow-partial calibrates the others and names why that one
    is left out; without it, one line names the camera and the file before any detection runs."""
    videos = tmp_path / "session"
    videos.mkdir()
    for c in range(3):
        (videos / f"cam{c}.mp4").symlink_to(shared_data / f"caliscope_4cam_charuco/calibration/extrinsic/cam_{c}.mp4")
    (videos / "cam3.mp4").write_bytes(b"\x00garbage" * 500)
    board = tmp_path / "board.toml"
    board.write_text(CHARUCO_TOML)
    out = tmp_path / "calib"
    args = ["calibrate", "rig", str(videos), "--board", str(board), "--board-frames", "6", "--workers", "1",
            "-o", str(out)]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 2 and "Traceback" not in res.output
    assert f"camera cam3: {videos / 'cam3.mp4'}: cannot open video" in res.output.strip().splitlines()[-1]
    assert not out.exists()
    res = CliRunner().invoke(cli, [*args, "--allow-partial"])
    assert res.exit_code == 0, res.output
    assert f"left out: camera cam3: {videos / 'cam3.mp4'}: cannot open video" in res.output
    assert "3 cameras (board)" in res.output and "PARTIAL, cam3 left out" in res.output
    assert load_cameras(out / "cameras.json").ids == ("cam0", "cam1", "cam2")
    report = json.loads((out / "report.json").read_text())
    assert report["partial"] and report["missing"] == {"cam3": f"{videos / 'cam3.mp4'}: cannot open video"}


def write_take(folder, shared_data, frames: int = 20) -> None:
    """A take folder (DESIGN.md) holding 20 synchronized frames of the caliscope cameras as MJPEG."""
    import csv

    import cv2

    root = shared_data / "caliscope_4cam_charuco" / "calibration" / "extrinsic"
    (folder / "cams").mkdir(parents=True)
    rows = []
    for c in range(4):
        cap = cv2.VideoCapture(str(root / f"cam_{c}.mp4"))
        writer = cv2.VideoWriter(str(folder / "cams" / f"c{c}.mkv"), cv2.VideoWriter_fourcc(*"MJPG"), 6, (1280, 720))
        for k in range(57):
            ok, image = cap.read()
            if k % 3 or len(rows) >= frames * (c + 1):
                continue
            writer.write(image)
            # host clocks: 6 fps ticks, each camera a few ms late, like free-running webcams
            rows.append([f"c{c}", k // 3, 0, 1_000_000_000 + (k // 3) * 166_666_667 + 3_000_000 * c, 0, 0])
        writer.release()
    (folder / "take.json").write_text(json.dumps({"kind": "calibration", "cameras": [f"c{c}" for c in range(4)],
                                                  "fps": 6.0, "status": "complete"}))
    with open(folder / "frames.csv", "w", newline="") as f:
        csv.writer(f).writerows([["cam", "seq", "t_device_ns", "t_host_ns", "bytes", "flags"], *rows])


def test_rig_command_on_a_take_folder(shared_data, tmp_path):
    take = tmp_path / "take"
    write_take(take, shared_data)
    board = tmp_path / "board.toml"
    board.write_text(CHARUCO_TOML)
    out = tmp_path / "calib"
    res = CliRunner().invoke(cli, ["calibrate", "rig", str(take), "--board", str(board), "--workers", "2",
                                   "-o", str(out)])
    assert res.exit_code == 0, res.output
    report = json.loads((out / "report.json").read_text())
    assert set(report["cameras"]) == {"c0", "c1", "c2", "c3"}
    # the four cameras' frames were grouped on their host timestamps: the board fits in every view
    assert report["rms_px"] < 2 and abs(report["checks"]["scale"]["error_pct"]) < 2
