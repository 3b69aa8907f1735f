"""`manus-capture detect`: 2D hand keypoints in every frame of every camera of a take."""

from __future__ import annotations

import time
from pathlib import Path

import click

from dataset_tools.keypoints import hand_keypoint_detector
from dataset_tools.keypoints.keypoints2d import (
    REDETECT_EVERY,
    TakeKeypoints,
    box_source,
    detect_take_tasks,
    detect_tasks,
    load_boxes,
    write_keypoints_h5,
)
from manus_capture import __version__
from manus_capture.bars import Bars
from manus_core.errors import OutputExists
from manus_core.take import Take

from .cluster import cluster_options


@click.command("detect", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("take", type=click.Path(path_type=Path))
@click.option("--model", "model_name", default="mediapipe-hand", show_default=True,
              help="mediapipe-hand, mediapipe-hand-lite, mediapipe-hand-int8 (after `models quantize`), "
                   "or a SimCC/heatmap model spec (.toml).")
@click.option("--boxes", "boxes_path", type=click.Path(path_type=Path), default=None,
              help="Hand boxes per camera and frame (.npz: CAM -> (F,4) or (F,5) with the hand angle). "
                   "Default: MediaPipe's palm detector finds the hand.")
@click.option("--cameras", default=None, help="Comma-separated camera ids (default: all of the take).")
@click.option("-o", "--output", type=click.Path(path_type=Path), default=None,
              help="Output file (default: TAKE/keypoints2d.h5).")
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default="auto", show_default=True,
              help="onnxruntime provider: CUDA when available (auto), or forced.")
@click.option("--chunk", type=click.IntRange(1), default=16, show_default=True,
              help="Frames per network call with --boxes or --no-track.")
@click.option("--track/--no-track", default=True, show_default=True,
              help="Without --boxes: crop each frame around the previous frame's keypoints (one pass of the "
                   "keypoint model), the palm detector only where the hand is lost, as MediaPipe tracks; "
                   "--no-track runs the palm detector and two passes in every frame.")
@click.option("--redetect-every", type=click.IntRange(1), default=REDETECT_EVERY, show_default=True,
              help="When tracking, the palm detector looks afresh at every this many frames of a camera.")
@click.option("--min-score", type=click.FloatRange(0, 1), default=0.5, show_default=True,
              help="Palm detector score threshold.")
@click.option("--palm-tiles", is_flag=True,
              help="The palm detector also looks at square tiles of each wide frame: small hands are found "
                   "more often (in 74 % of the demo's views that see the hand, against 39 %), at four network "
                   "passes a look instead of one (docs/keypoints.md).")
@cluster_options("by camera and frame range")
@click.option("--frames-per-task", type=click.IntRange(1), default=256, show_default=True,
              help="Frames of one camera per task (rounded to whole chunks; when tracking, to whole "
                   "--redetect-every periods).")
@click.option("--force", is_flag=True, help="Overwrite an existing output file.")
def command(take: Path, model_name: str, boxes_path: Path | None, cameras: str | None, output: Path | None,
            device: str, chunk: int, track: bool, redetect_every: int, min_score: float, palm_tiles: bool,
            workers: int, scheduler: str | None, frames_per_task: int, force: bool) -> None:
    """Detect 2D hand keypoints (21 joints, MediaPipe order) in every view of TAKE.

    Writes TAKE/keypoints2d.h5: per camera, keypoints (F,21,3) [x, y, confidence] indexed by the
    camera's frame index (its rows of frames.csv), and the boxes used. See docs/keypoints.md.
    """
    tk = Take(take)
    output = output or tk.path / "keypoints2d.h5"
    if output.exists() and not force:
        raise OutputExists(f"{output}: exists (use --force to overwrite)")
    cams = tuple(c.strip() for c in cameras.split(",")) if cameras else tk.cameras
    for cam in cams:
        tk.video_path(cam)  # every requested camera's video must exist before hours of work start
    for note in tk.missing_notes(cams):
        click.echo(f"warning: {note}", err=True)
    boxes = load_boxes(boxes_path, tk, cams) if boxes_path else None
    detector = hand_keypoint_detector(model_name, device=device)   # here too: a missing model stops us now
    total = sum(tk.readable_frames(c) for c in cams)
    start = time.perf_counter()
    model = str(Path(model_name).resolve()) if model_name.endswith(".toml") else model_name  # for other processes
    tasks = detect_take_tasks(tk, model, device, boxes, cams, chunk, min_score, frames_per_task, track, redetect_every,
                              palm_tiles)
    with Bars(unit="frame") as bars:
        result = detect_tasks(tk, tasks, workers, scheduler, progress=bars)
    elapsed = time.perf_counter() - start
    write_keypoints_h5(output, TakeKeypoints(
        result, detector.name, str(detector.model.session.path),
        box_source(boxes_path, track, palm_tiles),
        {"take": str(tk.path), "software": f"manus-capture {__version__}",
         "providers": ",".join(detector.providers)}))
    found = sum(int((r.keypoints[:, 0, 2] > 0.5).sum()) for r in result.values())
    click.echo(f"{output}: {len(cams)} cameras, {total} frames, hand found (confidence > 0.5) in "
               f"{found} ({100 * found / max(total, 1):.1f}%), {elapsed:.1f} s "
               f"({total / max(elapsed, 1e-9):.1f} frames/s, {detector.providers[0]})")
