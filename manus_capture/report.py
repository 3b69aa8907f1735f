"""The demo's HTML report: every stage's figures against ground truth, and pictures of each.

One self-contained folder: report.html refers to PNGs beside it (images/...), so it can be
copied or served as is.
"""

from __future__ import annotations

import html
import io
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from manus_core.fileio import write_atomic
from manus_core.skeleton import BONES

STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }
table { border-collapse: collapse; margin: 1em 0; }
td, th { border: 1px solid #ccc; padding: 4px 10px; text-align: left; vertical-align: top; }
th { background: #f3f3f3; }
figure { display: inline-block; margin: 0.5em; vertical-align: top; }
figure img { max-width: 520px; border: 1px solid #ddd; }
figcaption { font-size: 0.9em; color: #555; max-width: 520px; }
"""


def _value(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, dict):
        return ", ".join(f"{k}: {_value(x)}" for k, x in v.items())
    return str(v)


def stage_table(stages: Sequence[dict]) -> str:
    """Rows of stage, seconds and its figures."""
    rows = ["<tr><th>stage</th><th>seconds</th><th>figures against ground truth</th></tr>"]
    for s in stages:
        figures = "<br>".join(f"{html.escape(k)}: {html.escape(_value(v))}" for k, v in s["metrics"].items())
        rows.append(f"<tr><td>{html.escape(s['name'])}</td><td>{s['seconds']:.1f}</td><td>{figures}</td></tr>")
    return "<table>" + "".join(rows) + "</table>"


def text_table(stages: Sequence[dict]) -> str:
    """The stage table for a terminal: stage, seconds, figures (one per line)."""
    lines = [f"{'stage':<12} {'seconds':>8}  figures against ground truth", "-" * 72]
    for s in stages:
        figures = [f"{k} {_value(v)}" for k, v in s["metrics"].items()] or ["-"]
        lines.append(f"{s['name']:<12} {s['seconds']:>8.1f}  {figures[0]}")
        lines.extend(f"{'':<12} {'':>8}  {f}" for f in figures[1:])
    return "\n".join(lines)


def write_html(path: Path, title: str, summary: dict, stages: Sequence[dict],
               figures: Sequence[tuple[str, str]]) -> None:
    """report.html: the headline scores, the stage table and the figures (relative PNG path, caption)."""
    head = {k: summary[k] for k in ("contact_iou", "contact_f1", "baseline_iou", "baseline_f1", "views")
            if k in summary}
    headline = "<table>" + "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(_value(v))}</td></tr>"
                                   for k, v in head.items()) + "</table>"
    pictures = "".join(f'<figure><img src="{html.escape(src)}" alt="{html.escape(caption)}">'
                       f"<figcaption>{html.escape(caption)}</figcaption></figure>" for src, caption in figures)
    page = (f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<style>{STYLE}</style></head><body><h1>{html.escape(title)}</h1>"
            f"<h2>Contacts against the paint</h2>{headline}<h2>Stages</h2>{stage_table(stages)}"
            f"<h2>Pictures</h2>{pictures}</body></html>")
    write_atomic(path, page.encode())


def ablation_png(views: dict, baseline: float) -> bytes:
    """Contact IoU against the number of cameras the models were built from."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    counts = sorted(int(k) for k in views)
    fig, ax = plt.subplots(figsize=(5, 3.2), dpi=100)
    ax.plot(counts, [views[str(k)] if str(k) in views else views[k] for k in counts], "o-",
            label="Gaussian hand (MANUS)")
    ax.axhline(baseline, color="grey", linestyle="--", label="capsule template (all cameras)")
    ax.set_xlabel("cameras used to build the models")
    ax.set_ylabel("contact IoU")
    ax.legend(loc="lower right")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()


def mask_comparison(image: np.ndarray, pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """BGR picture: the frame dimmed, paint truth in green, prediction in red, both in yellow."""
    out = (np.asarray(image, np.float32) * 0.5).astype(np.uint8)
    out[truth & ~pred] = (0, 220, 0)
    out[pred & ~truth] = (0, 0, 230)
    out[pred & truth] = (0, 230, 230)
    return out


def keypoint_overlay(image: np.ndarray, detected: np.ndarray, projected: np.ndarray) -> np.ndarray:
    """BGR picture: detected 2D keypoints (21,3) as yellow dots, the fitted hand's projection (21,2)
    as its skeleton in magenta."""
    import cv2


    out = np.ascontiguousarray(image).copy()
    for a, b in BONES:
        pa, pb = projected[a], projected[b]
        if np.all(np.isfinite([*pa, *pb])):
            cv2.line(out, tuple(int(round(v)) for v in pa), tuple(int(round(v)) for v in pb), (255, 0, 255), 1,
                     cv2.LINE_AA)
    for x, y, conf in detected:
        if conf > 0 and np.isfinite(x) and np.isfinite(y):
            cv2.circle(out, (int(round(x)), int(round(y))), 2, (0, 255, 255), -1, cv2.LINE_AA)
    return out
