"""`manus-capture calibrate`: intrinsics of one camera, or the whole rig of a take."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from dataset_tools.calibration.boards import load_board
from dataset_tools.calibration.detect import detect_source
from dataset_tools.calibration.diagnose import diagnose_board
from dataset_tools.calibration.formats import save_cameras
from dataset_tools.calibration.frames import VIDEO_SUFFIXES, expand_inputs, read_frames, subsample
from dataset_tools.calibration.intrinsics import calibrate_intrinsics
from dataset_tools.calibration.rig import calibrate_rig
from manus_capture.bars import Bars
from manus_core.cameras import CameraRig
from manus_core.errors import BoardError


@click.group()
def command() -> None:
    """Calibrate one camera (intrinsics) or every camera of a take (rig)."""


@command.command("intrinsics")
@click.argument("inputs", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@click.option("--board", "board_file", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="board.toml describing the calibration target.")
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="cameras.json to write (one camera).")
@click.option("--camera-id", default=None, help="Id of the camera in the output (default: the input's name).")
@click.option("--frames", type=click.IntRange(min=4), default=200, show_default=True,
              help="Frames of a video to look at (evenly spread).")
@click.option("--max-views", type=click.IntRange(min=4), default=60, show_default=True,
              help="Views kept for the fit, chosen to cover the image.")
@click.option("--fix-k3", is_flag=True, help="Hold k3 at 0 (few views, or a narrow lens).")
@click.option("--force", is_flag=True, help="Overwrite an existing output.")
def intrinsics(inputs, board_file: Path, output: Path, camera_id, frames: int, max_views: int, fix_k3: bool,
               force: bool) -> None:
    """One camera's intrinsics from board IMAGES (files or folders) or one VIDEO."""
    if output.exists() and not force:
        raise click.UsageError(f"{output} exists; use --force to overwrite it")
    board = load_board(board_file)
    source = subsample(expand_inputs(inputs), frames)
    name = camera_id or Path(source.paths[0]).stem if source.is_video else camera_id or Path(source.paths[0]).parent.name
    total = len(source.frames) if source.frames else len(source.paths)
    with Bars(unit="frame") as bars:
        found, size = detect_source(source, board, progress=bars)
    if not found:
        sample = [g for _, g in read_frames(subsample(source, 5))]
        raise BoardError(f"camera {name}: no board in {total} frames: {diagnose_board(sample, board)}")
    result = calibrate_intrinsics(found, board, size, camera=name, max_views=max_views, fix_k3=fix_k3)
    rig = CameraRig((name,), result.K[None], result.dist[None], np.eye(3)[None], np.zeros((1, 3)),
                    np.array([size]), np.array([result.rms_px]))
    save_cameras(rig, output, "json")
    click.echo(f"wrote {output}: camera {name} {size[0]}x{size[1]}, fx={result.K[0, 0]:.2f} fy={result.K[1, 1]:.2f} "
               f"cx={result.K[0, 2]:.2f} cy={result.K[1, 2]:.2f}, RMS {result.rms_px:.3f} px over "
               f"{len(result.views)} views ({len(result.rejected)} rejected; board in {len(found)} of {total} frames), "
               f"coverage {result.coverage:.2f}")


@command.command("rig")
@click.argument("take", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--tags", "tags_file", type=click.Path(dir_okay=False, path_type=Path),
              help="tags.json: the tag layout of the walls (world frame, metres).")
@click.option("--board", "board_file", type=click.Path(dir_okay=False, path_type=Path),
              help="board.toml: a board seen by the cameras (intrinsics, or the board method).")
@click.option("--method", type=click.Choice(["auto", "tags", "board", "colmap", "both"]), default="auto",
              show_default=True, help="auto: tags when --tags is given, else board.")
@click.option("--intrinsics", "intrinsics_file", type=click.Path(exists=True, path_type=Path),
              help="Fixed intrinsics (cameras.json or any format `load_cameras` reads).")
@click.option("--allow-partial", is_flag=True,
              help="Leave out cameras that cannot be calibrated (the report marks the result partial).")
@click.option("--refine-tags", is_flag=True, help="Let each tag move a little (a layout measured by hand).")
@click.option("--tag-frames", type=click.IntRange(min=1), default=5, show_default=True,
              help="Frames per camera for tag detection (static cameras need few).")
@click.option("--board-frames", type=click.IntRange(min=4), default=200, show_default=True,
              help="Frames per camera for board detection.")
@click.option("--workers", type=click.IntRange(min=1), default=None, help="Processes for detection (default: CPUs).")
@click.option("-o", "--output", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="CALIB folder: cameras.json, exports, report.json/.md, cameras.png.")
@click.option("--force", is_flag=True, help="Replace an existing calibration in the output folder.")
def rig(take: Path, tags_file, board_file, method, intrinsics_file, allow_partial, refine_tags, tag_frames,
        board_frames, workers, output: Path, force: bool) -> None:
    """Calibrate every camera of TAKE (a take folder, or a folder of per-camera videos).

    With nothing else, a take of a session is calibrated from the session's tags.json (beside
    session.toml): every camera's intrinsics and pose from the tags it sees. --intrinsics or a
    --board give the intrinsics instead.
    """
    images, take_dir = _take_or_videos(take)
    if tags_file is None and board_file is None and method in ("auto", "tags", "colmap", "both"):
        tags_file = _session_tags(take)
    with Bars(unit="cam") as bars:
        result = calibrate_rig(images, take=take_dir, tags=tags_file, board=board_file, method=method,
                               intrinsics=intrinsics_file, allow_partial=allow_partial, tag_frames=tag_frames,
                               board_frames=board_frames, refine_tags=refine_tags, workers=workers, output=output,
                               force=force, progress=bars)
    for cam, why in result.missing.items():
        click.echo(f"  left out: camera {cam}: {why}", err=True)
    status = "PARTIAL, " + ", ".join(result.missing) + " left out" if result.partial else "complete"
    scene = result.extra.get("scene_points")
    if scene:  # millimetres rather than tenths: say which cameras to aim at more tags
        status += f"; {', '.join(scene)} short of tags, placed from scene features"
    click.echo(f"wrote {output}: {len(result.rig)} cameras ({result.method}), reprojection RMS {result.rms_px:.3f} px, "
               f"median {result.median_px:.3f} px over {len(result.obs)} observations; {status}")
    for tag, why in result.extra["checks"].get("layout", {}).get("disagreeing", {}).items():
        click.echo(f"  warning: tag {tag} disagrees with {tags_file}: {why}; left out", err=True)
    estimated = result.extra.get("intrinsics", {})
    if estimated:
        click.echo(f"  intrinsics from the tags: {len(estimated)} cameras (report.md gives their standard "
                   "deviations)")
    for cam, entry in estimated.items():
        if entry.get("weak"):
            click.echo(f"  warning: camera {cam}: weakly constrained ({'; '.join(entry['weak'])}): aim it at more "
                       "tags, or wave a board in front of it and pass --board", err=True)


def _session_tags(take: Path) -> Path:
    """The session's tags.json, beside session.toml (a take's parent folder, or the folder itself)."""
    for folder in (take, take.parent):
        if (folder / "tags.json").is_file():
            return folder / "tags.json"
    raise click.UsageError(f"no tags.json in {take.parent} or {take} (looked beside session.toml): "
                           "pass --tags FILE, or --board FILE for a board seen by the cameras")


def _take_or_videos(folder: Path):
    """A take folder (take.json) -> (None, folder); a folder of CAM.mp4/.mkv/... -> ({CAM: video}, None)."""
    if (folder / "take.json").is_file():
        return None, folder
    videos = {p.stem: p for p in sorted(folder.iterdir()) if p.suffix.lower() in VIDEO_SUFFIXES}
    if not videos:
        raise click.UsageError(f"{folder}: neither a take folder (take.json) nor a folder of per-camera videos")
    return videos, None

