"""The calibration report: report.json, report.md and a picture of the camera layout.

report.json holds, per camera, the reprojection error (RMS and median, pixels), the number of
observations and frames, the share of the image the observations cover, and the intrinsics; per
rig the overall error, the outliers, the cameras left out (with why) and a metric scale check:
board points (or tag corners) triangulated from the calibrated cameras, their neighbour distances
against the known square (or tag side).
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from manus_core.cameras import CameraRig
from manus_core.fileio import write_atomic
from manus_core.rotations import rotation_angle_deg

from ..triangulation import triangulate
from .result import RigCalibration


def scale_check(result: RigCalibration, pairs: np.ndarray, true_distance: float, static: bool = False) -> dict:
    """triangulation_check of a calibration's own observations (see there)."""
    obs = result.obs
    frame = np.zeros_like(obs.frame) if static else obs.frame
    return triangulation_check(result.rig, obs.cam, frame, obs.point, obs.xy, pairs, true_distance)


def triangulation_check(rig: CameraRig, cam: np.ndarray, frame: np.ndarray, point: np.ndarray, xy: np.ndarray,
                        pairs: np.ndarray, true_distance: float) -> dict:
    """Triangulate every (frame, point) seen by >= 2 cameras, reproject, and compare neighbour distances.

    cam (M,) camera index into rig, frame (M,), point (M,) ids, xy (M,2) raw pixels: one row per
    observation. pairs (P,2): point ids one known distance apart (board.neighbour_pairs(), or tag
    edges); for static points (wall tags) pass the same frame for all. Returns {"rmse_px",
    "median_px" (reprojection of the triangulated points), "pairs", "mean_m", "std_m", "true_m",
    "error_pct"}, or {} when nothing is seen twice.
    """
    n_points = int(point.max()) + 1
    keys = np.asarray(frame, np.int64) * n_points + point
    uniq, inverse = np.unique(keys, return_inverse=True)
    pts = np.full((len(rig), len(uniq), 3), np.nan)
    pts[cam, inverse, :2] = xy
    pts[cam, inverse, 2] = 1.0
    seen = np.isfinite(pts[..., 0]).sum(axis=0) >= 2
    if not seen.any():
        return {}
    X, _ = triangulate(rig, pts[:, seen], ransac=False)
    err = np.linalg.norm(rig.project(X) - pts[:, seen, :2], axis=2)
    err = err[np.isfinite(err)]
    # table (frame, point id) -> triangulated point, then every pair in every frame at once
    frames, frame_of = np.unique(uniq[seen] // n_points, return_inverse=True)
    table = np.full((len(frames), n_points), -1)
    table[frame_of, uniq[seen] % n_points] = np.arange(int(seen.sum()))
    pairs = pairs[(pairs < n_points).all(axis=1)]
    a, b = table[:, pairs[:, 0]].ravel(), table[:, pairs[:, 1]].ravel()
    ok = (a >= 0) & (b >= 0)
    out = {"rmse_px": float(np.sqrt(np.mean(err**2))), "median_px": float(np.median(err)), "points": int(seen.sum())}
    if ok.any():
        d = np.linalg.norm(X[a[ok]] - X[b[ok]], axis=1)
        d = d[np.isfinite(d)]
        out.update({"pairs": int(len(d)), "mean_m": float(d.mean()), "std_m": float(d.std()),
                    "true_m": float(true_distance), "error_pct": float(100 * (d.mean() - true_distance) / true_distance)})
    return out


def cross_check(a: RigCalibration, b: RigCalibration) -> dict:
    """Per camera: distance between the two centres (mm) and angle between the rotations (deg)."""
    common = [i for i in a.rig.ids if i in b.rig.ids]
    if not common:
        return {}
    ra, rb = a.rig.subset(common), b.rig.subset(common)
    dc = np.linalg.norm(ra.centers - rb.centers, axis=1) * 1000
    da = rotation_angle_deg(ra.R, rb.R)
    # where the two disagree by more than either is expected to err: look at those cameras
    disagree = [c for c, x, y in zip(common, dc, da) if x > 10 or y > 0.5]
    return {"cameras": {c: {"centre_mm": round(float(x), 3), "rotation_deg": round(float(y), 4)}
                        for c, x, y in zip(common, dc, da)}, "disagree": disagree,
            "centre_mm_median": float(np.median(dc)), "centre_mm_max": float(dc.max()),
            "rotation_deg_median": float(np.median(da)), "rotation_deg_max": float(da.max())}


def build_report(result: RigCalibration, inputs: dict | None = None, checks: dict | None = None) -> dict:
    """The report as a JSON-ready dict."""
    cams = {}
    for i, cam in enumerate(result.rig.ids):
        s = result.stats[cam]
        cams[cam] = {"rms_px": _r(s.rms_px), "median_px": _r(s.median_px), "observations": s.observations,
                     "frames": s.frames, "coverage": round(s.coverage, 3),
                     "centre_m": [round(float(x), 5) for x in result.rig.centers[i]],
                     "fx": _r(result.rig.K[i, 0, 0]), "fy": _r(result.rig.K[i, 1, 1]),
                     "cx": _r(result.rig.K[i, 0, 2]), "cy": _r(result.rig.K[i, 1, 2]),
                     "dist": [float(x) for x in result.rig.dist[i]]}
        if s.intrinsics:
            cams[cam]["intrinsics_alone"] = s.intrinsics
    return {"method": result.method, "partial": result.partial,
            "missing": result.missing, "cameras_calibrated": len(result.rig),
            "rms_px": _r(result.rms_px), "median_px": _r(result.median_px),
            "observations": int(len(result.obs)), "outliers_removed": int(result.outliers),
            "cameras": cams, "checks": checks or {},
            "details": _jsonable({k: v for k, v in result.extra.items() if k != "checks"}), "inputs": inputs or {}}


def _r(x: float) -> float | None:
    return None if x is None or not np.isfinite(x) else round(float(x), 4)


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value


def report_markdown(report: dict) -> str:
    """A human summary of report.json."""
    lines = [f"# Calibration report ({report['method']})", ""]
    if report["partial"]:
        lines += ["**PARTIAL RESULT**: these cameras are not calibrated:", ""]
        lines += [f"- `{c}`: {why}" for c, why in report["missing"].items()] + [""]
    lines += [f"- cameras calibrated: {report['cameras_calibrated']}",
              f"- reprojection error: RMS {report['rms_px']} px, median {report['median_px']} px "
              f"over {report['observations']} observations ({report['outliers_removed']} outliers removed)"]
    scale = report["checks"].get("scale")
    if scale:
        lines.append(f"- scale check: {scale['pairs']} neighbour distances, mean {scale['mean_m'] * 1000:.2f} mm "
                     f"(std {scale['std_m'] * 1000:.2f}) against {scale['true_m'] * 1000:.2f} mm "
                     f"({scale['error_pct']:+.2f} %)")
    cross = report["checks"].get("cross_check")
    if cross:
        lines.append(f"- COLMAP vs tags: centres differ by {cross['centre_mm_median']:.2f} mm median "
                     f"({cross['centre_mm_max']:.2f} max), rotations by {cross['rotation_deg_median']:.3f} deg "
                     f"median ({cross['rotation_deg_max']:.3f} max)"
                     + (f"; more than 10 mm or 0.5 deg apart: {', '.join(cross['disagree'])}" if cross["disagree"] else ""))
    layout = report["checks"].get("layout")
    if layout:
        lines.append(f"- tags.json against the images: {layout['tags_checked']} tags triangulated, corners "
                     f"{layout['median_mm']} mm median (max {layout['max_mm']}) from their listed place")
        lines += [f"- **warning**, tag {t} disagrees with tags.json and was left out: {why}"
                  for t, why in layout["disagreeing"].items()]
    lines += ["", "| camera | RMS px | median px | observations | frames | coverage | fx | fy |",
              "|---|---|---|---|---|---|---|---|"]
    for cam, c in report["cameras"].items():
        lines.append(f"| {cam} | {c['rms_px']} | {c['median_px']} | {c['observations']} | {c['frames']} | "
                     f"{c['coverage']:.2f} | {c['fx']:.1f} | {c['fy']:.1f} |")
    estimated = report["details"].get("intrinsics", {})
    if estimated:
        weak = {c: e["weak"] for c, e in estimated.items() if e.get("weak")}
        lines += ["", "## Intrinsics estimated from the tags", ""]
        lines += [f"- **warning**, `{c}` is weakly constrained: {'; '.join(w)}. Aim it at more tags, or wave a "
                  "board in front of it and pass --board." for c, w in weak.items()]
        lines += ["", "| camera | model | corners | reach | sd fx px | sd cx px | sd cy px | sd k1 | sd centre mm |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for cam, e in estimated.items():
            sd = e.get("sd")
            cells = [f"{sd[k]:.3g}" for k in ("fx", "cx", "cy", "k1", "centre_mm")] if sd else ["-"] * 5
            lines.append(f"| {cam} | {e.get('model') or 'borrowed'} | {e.get('points', '-')} | {e.get('reach', '-')} | "
                         + " | ".join(cells) + " |")
    lines += ["", "A good calibration: RMS below 0.5 px on every camera (below 1 px with webcams and motion),",
              "coverage above 0.3, the scale check within 0.5 %. See docs/calibration.md.", ""]
    return "\n".join(lines)


def layout_png(result: RigCalibration, points: np.ndarray | None = None) -> bytes:
    """PNG of the camera centres and viewing directions, coloured by reprojection RMS."""
    rig = result.rig
    centres = rig.centers
    rms = np.array([result.stats[c].rms_px for c in rig.ids])
    fig = Figure(figsize=(7, 6), dpi=110)  # no pyplot: no global backend or figure list to manage
    ax = fig.add_subplot(projection="3d")
    if points is not None and len(points):
        ax.scatter(*points.T, s=2, c="0.6", label="targets")
    span = float(np.ptp(np.vstack([centres] + ([points] if points is not None and len(points) else [])), axis=0).max())
    look = rig.R[:, 2, :] * 0.08 * max(span, 1e-3)  # optical axes in the world frame (rows of R)
    sc = ax.scatter(*centres.T, c=rms, cmap="viridis_r", s=40, depthshade=False)
    ax.quiver(*centres.T, *look.T, color="k", linewidth=0.7)
    if len(rig) <= 60:
        for c, p in zip(rig.ids, centres):
            ax.text(*p, f" {c}", fontsize=6)
    fig.colorbar(sc, ax=ax, shrink=0.7, label="reprojection RMS (px)")
    everything = np.vstack([centres] + ([points] if points is not None and len(points) else []))
    mid, half = everything.mean(axis=0), max(float(np.ptp(everything, axis=0).max()) / 2, 1e-3) * 1.1
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_zlim(mid[2] - half, mid[2] + half)
    ax.set_box_aspect((1, 1, 1))  # metres look like metres on every axis
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.set_title(f"{len(rig)} cameras, RMS {result.rms_px:.3f} px")
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def write_report(result: RigCalibration, folder: str | Path, report: dict,
                 points: np.ndarray | None = None) -> list[Path]:
    """report.json, report.md and cameras.png into `folder`, atomically."""
    folder = Path(folder)
    out = [folder / "report.json", folder / "report.md", folder / "cameras.png"]
    write_atomic(out[0], json.dumps(report, indent=1).encode())
    write_atomic(out[1], report_markdown(report).encode())
    write_atomic(out[2], layout_png(result, points))
    return out

