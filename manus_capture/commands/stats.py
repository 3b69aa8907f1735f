"""`manus-capture stats`: per take frames, coverage, reprojection error, IK residual, grip aperture."""

from __future__ import annotations

import io
import json
from pathlib import Path

import click
import numpy as np

from manus_capture.bars import Bars
from manus_core.dataset import FLAGS, read_dataset
from manus_core.errors import OutputExists
from manus_core.fileio import write_atomic

THUMB_TIP = 4
OTHER_TIPS = {"index": 8, "middle": 12, "ring": 16, "pinky": 20}


def take_stats(ann) -> dict:
    """Summary numbers of one TakeAnnotation (NaN-aware; frames without a hand are not averaged)."""
    views = ann.keypoints3d_views.astype(np.float64)
    found = np.isfinite(ann.keypoints3d).all(-1)
    err = ann.keypoints3d_error_px[found]
    res = ann.ik_residual_m[np.isfinite(ann.ik_residual_m)] * 1e3
    n_t = len(ann.frame_ns)
    duration = (ann.frame_ns[-1] - ann.frame_ns[0]) / 1e9 if n_t > 1 else 0.0

    def pct(x: np.ndarray, q: float) -> float | None:
        return float(np.percentile(x, q)) if len(x) else None

    return {
        "frames": n_t, "cameras": len(ann.cameras), "duration_s": duration,
        "frames_fitted": int(np.isfinite(ann.joint_angles_raw[:, 0]).sum()),
        "joints_triangulated_pct": 100.0 * float(found.mean()) if n_t else 0.0,
        "views_per_joint_mean": float(views.mean()) if n_t else 0.0,
        "views_per_joint_min": int(views.min()) if n_t else 0,
        "views_per_joint": [float(v) for v in views.mean(0)] if n_t else [],
        "reprojection_px_median": pct(err, 50), "reprojection_px_p95": pct(err, 95),
        "ik_residual_mm_median": pct(res, 50), "ik_residual_mm_p95": pct(res, 95),
        "flags": {name: int(((ann.flags & bit) > 0).sum()) for name, bit in FLAGS.items()},
    }


def grip_aperture(ann) -> np.ndarray:
    """Thumb tip to each other fingertip (T,4) in metres, from the filtered fitted hand."""
    joints = ann.fitted_joints(filtered=True)
    return np.linalg.norm(joints[:, list(OTHER_TIPS.values())] - joints[:, THUMB_TIP, None], axis=-1)


def plot_apertures(anns: list, path: Path) -> None:
    """One panel per take: grip aperture (mm) over time (s); written atomically as PNG."""
    # matplotlib takes a second to import and only the plot needs it; Agg must come before pyplot
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(anns), 1, figsize=(8, 2.6 * len(anns)), squeeze=False, sharex=False)
    for ax, ann in zip(axes[:, 0], anns):
        t = (ann.frame_ns - ann.frame_ns[0]) / 1e9 if len(ann.frame_ns) else ann.frame_ns
        ap = grip_aperture(ann) * 1e3
        for k, name in enumerate(OTHER_TIPS):
            ax.plot(t, ap[:, k], label=f"thumb-{name}", lw=1.2)
        ax.set_title(ann.key, fontsize=9)
        ax.set_ylabel("aperture (mm)")
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("time (s)")
    axes[0, 0].legend(fontsize=7, ncol=4, loc="upper right")
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=100)
    plt.close(fig)
    write_atomic(path, buffer.getvalue())


def _fmt(x, unit: str = "") -> str:
    return "-" if x is None else f"{x:.2f}{unit}"


@click.command("stats", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("--take", "selected", multiple=True, help="Only these takes (SESSION/TAKE); repeatable.")
@click.option("--plot", type=click.Path(path_type=Path), default=None,
              help="Grip aperture plot (PNG). Default: DATASET.aperture.png beside the dataset.")
@click.option("--json", "json_path", type=click.Path(path_type=Path), default=None,
              help="Also write the numbers as JSON.")
@click.option("--force", is_flag=True, help="Overwrite an existing plot or JSON file.")
def command(dataset: Path, selected: tuple[str, ...], plot: Path | None, json_path: Path | None, force: bool) -> None:
    """Summarize DATASET: per take frames, coverage (views per joint), reprojection error, IK
    residual, frame flags, and a plot of the grip aperture (thumb tip to each fingertip) over time."""
    ds = read_dataset(dataset)
    keys = list(selected) or ds.takes
    unknown = [k for k in keys if k not in ds]
    if unknown:
        raise click.BadParameter(f"{dataset}: no take {unknown[0]!r} (takes: {', '.join(ds.takes) or 'none'})",
                                 param_hint="--take")
    plot = plot or dataset.with_suffix(".aperture.png")
    for path in (plot, json_path):
        if path is not None and path.exists() and not force:
            raise OutputExists(f"{path}: exists (use --force to overwrite)")
    anns, table, notes = [], {}, []
    with Bars(unit="take") as bars:
        bars("stats", 0, len(keys))
        for done, key in enumerate(keys, 1):
            stages = ds.stages(key)
            table[key] = {"stages": sorted(stages)}
            if "annotate" in stages:
                ann = ds[key]
                anns.append(ann)
                table[key].update(take_stats(ann))
            for stage in sorted(stages - {"annotate"}):
                other = ds.recording_differences(key, stage)
                if other:
                    table[key][f"{stage}_of_another_recording"] = other
                    notes.append(f"note: {key}: its {stage} results and its annotation are of different recordings "
                                 f"({'; '.join(other)}): redo whichever ran before the take was recorded again")
            bars("stats", done, len(keys))
    header = f"{'take':<28} {'frames':>6} {'fitted':>6} {'views/joint':>11} {'joints %':>8} " \
             f"{'reproj px (med/p95)':>19} {'IK mm (med/p95)':>15}  results"
    click.echo(header)
    for key, s in table.items():
        results = "+".join(s["stages"])
        if "frames" not in s:
            click.echo(f"{key:<28} {'not annotated: run annotate on it for these numbers':<70}  {results}")
            continue
        click.echo(f"{key:<28} {s['frames']:>6} {s['frames_fitted']:>6} "
                   f"{s['views_per_joint_mean']:>6.1f} (>={s['views_per_joint_min']:<2}) "
                   f"{s['joints_triangulated_pct']:>8.1f} "
                   f"{_fmt(s['reprojection_px_median']):>9}/{_fmt(s['reprojection_px_p95']):<9} "
                   f"{_fmt(s['ik_residual_mm_median']):>7}/{_fmt(s['ik_residual_mm_p95']):<7}  {results}")
    for note in notes:
        click.echo(note, err=True)
    if anns:
        plot_apertures(anns, plot)
    if json_path is not None:
        write_atomic(json_path, (json.dumps(table, indent=1) + "\n").encode())
    total = sum(s.get("frames", 0) for s in table.values())
    fitted = sum(s.get("frames_fitted", 0) for s in table.values())
    bare = [key for key, s in table.items() if "frames" not in s]
    click.echo(f"{dataset}: {len(table)} takes, {total} frames, hand fitted in {fitted} "
               f"({100.0 * fitted / max(total, 1):.1f}%)" + (f"; not annotated: {', '.join(bare)}" if bare else "")
               + (f"; aperture plot {plot}" if anns else ""))
