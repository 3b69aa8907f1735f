"""sync_report.json (DESIGN.md), its Markdown twin and the timeline PNG, from a SyncResult."""

from __future__ import annotations

import io
import math
from collections.abc import Sequence

import numpy as np

from .analysis import SyncResult
from .files import TakeFiles
from .grouping import spread_floor_ns
from .optical import Flash

REPORT_VERSION = 1


def noise_range_ns(sigma_ns: float, n: int) -> float:
    """Expected max - min of n exposures that coincide but are stamped with N(0, sigma) noise:
    the spread timestamp noise alone shows (sigma * 2.85 for 8 cameras, * 4.6 for 53)."""
    if n < 2 or not np.isfinite(sigma_ns):
        return 0.0
    # here: scipy.special's import is 0.14 s of the start-up of every command that reads a take
    from scipy.special import ndtr

    x = np.linspace(-9.0, 9.0, 3601)
    cdf = ndtr(x)
    return float(sigma_ns * np.sum(1.0 - cdf ** n - (1.0 - cdf) ** n) * (x[1] - x[0]))


def take_state(status: str | None) -> str:
    """How a take ended, in the report's words ("" for a complete take)."""
    if status in (None, "complete"):
        return ""
    return "killed while recording" if status == "recording" else f"take {status}"


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3f}"


def _r(x: float | None, digits: int = 4) -> float | None:
    return None if x is None or not np.isfinite(x) else round(float(x), digits)


def _stats(values: np.ndarray) -> dict:
    v = values[np.isfinite(values)]
    if v.size == 0:
        return {"median": None, "p95": None, "p99": None, "max": None}
    return {"median": _r(np.median(v)), "p95": _r(np.percentile(v, 95)), "p99": _r(np.percentile(v, 99)),
            "max": _r(v.max())}


def build_report(result: SyncResult, optical: dict | None = None, take: str | None = None,
                 files: TakeFiles | None = None) -> dict:
    """sync_report.json (DESIGN.md) from a SyncResult, an optional optical check and the checks of
    the take's files (status, videos, unknown cameras)."""
    s = result.settings
    g = result.groups
    period = g.period_ns
    reasons: list[str] = list(files.reasons) if files else []
    notes: list[str] = list(files.notes) if files else []
    edges = result.edge_drops if result.edge_drops is not None else np.zeros((len(result.cameras), 2), np.int64)
    cameras = {}
    for c, cam in enumerate(result.cameras):
        ch, fit = cam.check, cam.fit
        dropped = int(ch.dropped_seq.size + edges[c].sum())
        span = cam.rows - ch.duplicate_seq + dropped
        drop_pct = 100.0 * dropped / span if span else 0.0
        cameras[cam.id] = {
            "frames_received": cam.rows,
            "frames_dropped": dropped,
            "dropped_seq": ch.dropped_seq.tolist(),
            "dropped_before_first": int(edges[c, 0]),
            "dropped_after_last": int(edges[c, 1]),
            "clock_offset_ms": _r(fit.offset_ns / 1e6) if fit and fit.offset_ns is not None else None,
            "drift_ppm": _r(fit.drift_ppm, 3) if fit else None,
            "interval_std_ms": _r(cam.interval_std_ns / 1e6),
            "offset_se_ms": _r(fit.offset_se_ns / 1e6) if fit else None,
            "drift_se_ppm": _r(fit.drift_se_ppm, 3) if fit else None,
            "residual_ms": _r(fit.residual_ns / 1e6) if fit else None,
            "latency_floor_ms": _r(fit.latency_ns / 1e6) if fit and cam.latency_known else None,
            "phase_ms": _r(g.camera_phase_ns[c] / 1e6),
            # device-clock intervals are long by the drift; host arrival intervals are not
            "fps_measured": _r(1e9 / cam.interval_mean_ns * (1 + fit.drift_ppm * 1e-6 if cam.device_clock else 1.0), 3)
            if fit and cam.interval_mean_ns > 0 else None,
            "duplicate_seq": ch.duplicate_seq,
            "reordered_seq": ch.reordered_seq,
            "seq_discontinuities": ch.discontinuities,
            "duplicate_timestamps": ch.duplicate_device_ts,
            "nonmonotonic_timestamps": ch.backwards_device_ts,
            "host_backwards": ch.backwards_host_ts,
            "unassigned_frames": int(g.unassigned[c]),
            "early_arrivals": cam.early_arrivals,
            "device_clock": cam.device_clock,
            **(files.cameras.get(cam.id, {}) if files else {}),
        }
        if cam.rows == 0 or fit is None:
            reasons.append(f"{cam.id}: no usable frames")
            continue
        bad = [f"{n} {what}" for n, what in ((ch.duplicate_seq, "repeated sequence numbers"),
                                              (ch.duplicate_device_ts, "duplicate device timestamps"),
                                              (ch.backwards_device_ts, "device timestamps going backwards"),
                                              (ch.backwards_host_ts, "host timestamps going backwards"),
                                              (ch.discontinuities, "sequence discontinuities"),
                                              (cam.early_arrivals, "frames that arrived over 1 ms before "
                                               + ("their timestamps allow (timestamps that jump)" if cam.device_clock
                                                  else "a steady frame rate allows (the rate changed)"))) if n]
        if bad:
            reasons.append(f"{cam.id}: {', '.join(bad)}")
        if drop_pct > s.max_drop_pct:
            reasons.append(f"{cam.id}: {drop_pct:.2f}% of frames dropped (limit {s.max_drop_pct:g}%)")
        if not cam.device_clock:
            notes.append(f"{cam.id}: no device timestamps; exposures assumed at a steady rate from the "
                         "sequence numbers")
        if abs(fit.drift_ppm) > 1000:
            reasons.append(f"{cam.id}: device clock runs {fit.drift_ppm:.0f} ppm off the host's "
                           "(timestamps in another unit?)")
    spread = g.spread_ns / 1e6
    members = np.count_nonzero(g.frame_index >= 0, axis=1)
    valid = spread[np.isfinite(spread)]
    within = 100.0 * np.count_nonzero(valid <= s.tolerance_ms) / valid.size if valid.size else None
    stats = _stats(spread)
    floor_t = spread_floor_ns(g.exposure_ns - g.t0_ns, period) / 1e6
    floor = float(np.nanmedian(floor_t)) if np.isfinite(floor_t).any() else math.nan
    # what grouping adds to the phases: nothing where each group's members are its tightest span
    above = _stats(spread - floor_t)
    free_run = result.sync == "free-run"
    tolerance_met = None if stats["p95"] is None else stats["p95"] <= s.tolerance_ms
    if free_run and above["p95"] is not None and above["p95"] > s.tolerance_ms:
        reasons.append(f"exposure spread p95 {above['p95']:.2f} ms above what the cameras' phases allow "
                       f"(> {s.tolerance_ms:g} ms): frames grouped away from their tick (timestamps that jump?)")
    elif not free_run and tolerance_met is False:
        reasons.append(f"exposure spread p95 {stats['p95']:.2f} ms > {s.tolerance_ms:g} ms")
    if free_run and len(result.cameras) > 1:
        notes.append(f"free-run: the cameras' frame phases keep exposures {floor:.3f} ms apart (median over groups), "
                     "so no grouping of these frames can be tighter: the verdict judges the spread above this "
                     f"floor, not the {s.tolerance_ms:g} ms tolerance. Exposures within {s.tolerance_ms:g} ms need "
                     "triggered cameras (sync = \"hardware-trigger\" in rig.toml)")
    latency_known = all(c.latency_known for c in result.cameras)
    if not latency_known:
        notes.append("the transfer latency floor (mid-exposure -> host arrival) is not given for every "
                     "camera: clock offsets are device minus earliest host arrival, and exposure times "
                     "carry each camera's floor (cameras whose floors differ look that much apart)")
    fits = [c.fit for c in result.cameras if c.fit is not None]
    # consecutive intervals differ by two timestamps' noise (and, triggered, two exposures' jitter)
    jitter = [c.interval_std_ns / math.sqrt(2) for c in result.cameras if np.isfinite(c.interval_std_ns)]
    noise = noise_range_ns(float(np.median(jitter)) if jitter else math.nan,
                           int(np.median(members)) if members.size else 0) / 1e6
    timing = {
        "latency_floor_known": latency_known,
        "fit_se_ms": _r(max((f.offset_se_ns for f in fits), default=math.nan) / 1e6),
        "timestamp_jitter_ms": _r(max(jitter, default=math.nan) / 1e6),
        "transfer_jitter_ms": _r(max((f.residual_ns for f in fits), default=math.nan) / 1e6),
        "spread_noise_ms": _r(noise),
    }
    if result.sync != "free-run" and stats["median"] is not None and stats["median"] <= 1.5 * noise:
        notes.append(f"{result.sync}: the median spread {stats['median']:.3f} ms is what timestamp noise "
                     f"alone shows ({noise:.3f} ms): the exposures are at least this close")
    if optical is not None:
        entries = optical["cameras"]
        seen = [cam for cam, e in entries.items() if e["flashes_seen"]]
        for cam, entry in entries.items():
            if entry["consistent"] is False:
                reasons.append(f"optical check: {cam}: the flashes put its exposures at times that exclude "
                               "each other (timestamps that jump, or a flash misread)")
            elif entry["error_ms"] is not None and entry["error_ms"] > s.optical_tolerance_ms:
                lo, hi = entry["exposure_error_ms"]
                reasons.append(f"optical check: {cam}: true exposures lie {lo:+.2f}..{hi:+.2f} ms from where "
                               "its timestamps put them")
            elif seen and not entry["flashes_seen"] and cameras[cam]["frames_received"]:
                reasons.append(f"optical check: {cam}: saw none of the flashes {len(seen)} other cameras saw "
                               "where its timestamps put them")
        if optical["flashes"] and not seen:
            notes.append("optical check: no camera saw a flash (scene too dark, or the LEDs were not in view)")
    return {
        "version": REPORT_VERSION,
        "take": take,
        "fps": result.fps,
        "sync": result.sync,
        "t0_ns": result.t0_ns,
        "cameras": cameras,
        "groups": int(g.frame_index.shape[0]),
        "complete_groups": int(np.count_nonzero(members == len(result.cameras))),
        "spread_ms": stats,
        "within_3ms_pct": _r(within, 3),
        "spread_floor_ms": _r(floor),
        "spread_above_floor_ms": above,
        "tolerance_met": tolerance_met,
        "timing": timing,
        "optical_check": optical,
        "take_status": files.status if files else None,
        "unknown_camera_rows": dict(files.unknown_camera_rows) if files else {},
        "verdict": "pass" if not reasons else "fail",
        "reasons": reasons,
        "notes": notes,
        "settings": {"tolerance_ms": s.tolerance_ms, "max_drop_pct": s.max_drop_pct,
                     "optical_tolerance_ms": s.optical_tolerance_ms},
    }


def report_markdown(report: dict) -> str:
    """sync_report.md: the same numbers for people."""
    state = take_state(report.get("take_status"))
    lines = [f"# Sync report: {report['take'] or 'take'}", "",
             f"**Verdict: {report['verdict'].upper()}** ({report['sync']}, {report['fps']:g} FPS, "
             f"{len(report['cameras'])} cameras{', ' + state if state else ''})", ""]
    lines += [f"- {r}" for r in report["reasons"]] + ([""] if report["reasons"] else [])
    sp = report["spread_ms"]
    fmt = _fmt
    lines += ["## Frame groups", "",
              f"{report['groups']} groups on the nominal ticks, {report['complete_groups']} with every camera.", "",
              "Exposure spread within a group (ms): "
              f"median {fmt(sp['median'])}, p95 {fmt(sp['p95'])}, p99 {fmt(sp['p99'])}, max {fmt(sp['max'])}; "
              f"{fmt(report['within_3ms_pct'])}% of groups within {report['settings']['tolerance_ms']:g} ms. "
              f"Frame phases alone allow no less than {fmt(report['spread_floor_ms'])} ms; the spread lies "
              f"p95 {fmt(report['spread_above_floor_ms']['p95'])} ms above that.", ""]
    if report.get("frame_groups"):
        lines += [f"These groups are saved in {report['frame_groups']}; annotate and segment work on them.", ""]
    lines += ["## How well the timestamps are known", ""]
    t = report["timing"]
    lines += [f"- latency floor given for every camera: {'yes' if t['latency_floor_known'] else 'no'}",
              f"- clock fit standard error (worst camera): {fmt(t['fit_se_ms'])} ms",
              f"- device timestamp jitter (worst camera, upper bound): {fmt(t['timestamp_jitter_ms'])} ms",
              f"- transfer jitter above the envelope (worst camera, median): {fmt(t['transfer_jitter_ms'])} ms", ""]
    if report["notes"]:
        lines += ["## Notes", ""] + [f"- {n}" for n in report["notes"]] + [""]
    lines += ["## Cameras", "",
              "| camera | frames | video | dropped | offset ms | drift ppm | interval std ms | phase ms | flags |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    for cam, c in report["cameras"].items():
        flags = [f"{k}={c[k]}" for k in ("duplicate_seq", "duplicate_timestamps", "nonmonotonic_timestamps",
                                         "host_backwards", "seq_discontinuities", "unassigned_frames",
                                         "early_arrivals", "dropped_before_first", "dropped_after_last")
                 if c.get(k)]
        video = c.get("video_frames", "n/a") if c.get("video_problem") != "missing" else "missing"
        lines.append(f"| {cam} | {c['frames_received']} | {video} | {c['frames_dropped']} | {fmt(c['clock_offset_ms'])} | "
                     f"{fmt(c['drift_ppm'])} | {fmt(c['interval_std_ms'])} | {fmt(c['phase_ms'])} | "
                     f"{' '.join(flags)} |")
    opt = report["optical_check"]
    if opt:
        lines += ["", "## Optical check", "",
                  f"{len(opt['flashes'])} LED flashes. Exposure error = true minus timestamp-predicted "
                  "mid-exposure, as bounded by the frames where each flash starts and ends.", "",
                  "| camera | flashes seen | exposure error ms | measured offset ms | predicted offset ms |",
                  "|---|---:|---|---|---:|"]
        for cam, c in opt["cameras"].items():
            err, mo = c["exposure_error_ms"], c["measured_offset_ms"]
            err = "n/a" if err is None else f"{err[0]:+.3f} .. {err[1]:+.3f}"
            mo = "n/a" if mo is None else f"{mo[0]:.3f} .. {mo[1]:.3f}"
            lines.append(f"| {cam} | {c['flashes_seen']} | {err} | {mo} | {fmt(c['predicted_offset_ms'])} |")
    return "\n".join(lines) + "\n"


def timeline_png(result: SyncResult, flashes: Sequence[Flash] = (), max_points: int = 4000) -> bytes:
    """A PNG: each camera's exposure offset from its group's tick over time, with drops marked."""
    # matplotlib takes a second to import and only the written report draws
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    g = result.groups
    n = len(result.cameras)
    fig = Figure(figsize=(11, 3.0 + 0.12 * n), dpi=100)
    FigureCanvasAgg(fig)
    ax_off, ax_drop = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [2, 1]})
    t_sec = (g.frame_ns - result.t0_ns) / 1e9
    step = max(1, t_sec.size // max_points)
    cmap = matplotlib.colormaps["tab20"]
    for c, cam in enumerate(result.cameras):
        dev = (g.exposure_ns[::step, c] - g.frame_ns[::step]) / 1e6
        # dots, not lines: a free-running camera whose phase drifts across a group boundary jumps
        # by a whole period there
        ax_off.plot(t_sec[::step], dev, ".", ms=1.5, color=cmap(c % 20), label=cam.id if n <= 12 else None)
        dropped = cam.check.dropped_seq
        if dropped.size and cam.fit is not None:
            o = cam.check.order
            # drops sit between received frames: interpolate their time on the sequence numbers
            t_drop = np.interp(dropped, cam.seq[o], cam.exposure_ns[o])
            ax_drop.plot((t_drop - result.t0_ns) / 1e9, np.full(dropped.size, c), "|", color="tab:red", ms=8)
    for f in flashes:
        for ax in (ax_off, ax_drop):
            ax.axvspan((f.on_ns - result.t0_ns) / 1e9, (f.on_ns + f.duration_ns - result.t0_ns) / 1e9,
                       color="gold", alpha=0.3, lw=0)
    ax_off.set_ylabel("exposure - tick (ms)")
    ax_off.set_title(f"{result.sync}, {result.fps:g} FPS: exposure offsets from the group tick")
    if n <= 12:
        ax_off.legend(fontsize=7, ncol=min(n, 6), loc="upper right", markerscale=5)
    ax_drop.set_ylim(-1, n)
    ax_drop.set_yticks(range(n))
    ax_drop.set_yticklabels([c.id for c in result.cameras], fontsize=max(4, 9 - n // 10))
    ax_drop.set_ylabel("drops")
    ax_drop.set_xlabel("time since tick 0 (s)")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()
