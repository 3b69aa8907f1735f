"""LED flashes from take.json's LED log, and the optical check: where the images see each flash
begin and end, against where the timestamps put the exposures (docs/sync.md)."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from manus_core.progress import Progress, silent

from .analysis import CameraSync


@dataclass(frozen=True)
class Flash:
    """An LED flash from the command log: it started somewhere in [on_lo_ns, on_hi_ns] (sent ..
    acknowledged) and lasted duration_ns (timed by the controller)."""

    on_lo_ns: int
    on_hi_ns: int
    duration_ns: int
    level: float

    @property
    def on_ns(self) -> float:
        return (self.on_lo_ns + self.on_hi_ns) / 2


def led_flashes(log: Iterable[Mapping]) -> list[Flash]:
    """The flashes of a take.json LED log (rig.leds records: ASCII `FLASH` with args [ms, level
    0..1000] acknowledged `ok`, or DMX `FLASH` with `ms` and `levels`, status `sent`)."""
    out = []
    for rec in log:
        if not isinstance(rec, Mapping) or rec.get("cmd") != "FLASH" or rec.get("status") not in ("ok", "sent"):
            continue
        sent = rec.get("t_send_ns")
        done = rec.get("t_ack_ns") or rec.get("t_done_ns") or sent
        args = rec.get("args") or []
        ms = rec.get("ms", args[0] if args else None)
        if not isinstance(sent, int) or not isinstance(done, int) or not isinstance(ms, (int, float)):
            continue
        if "levels" in rec and rec["levels"]:
            level = float(max(rec["levels"]))
        else:
            level = float(args[1]) / 1000 if len(args) > 1 else 1.0
        out.append(Flash(int(sent), int(done), int(round(ms * 1e6)), level))
    return sorted(out, key=lambda f: f.on_lo_ns)


BrightnessFn = Callable[[str, np.ndarray], np.ndarray]
"""brightness(cam, frame_indices (sorted, unique)) -> mean image brightness (n,) of those frames."""


def _onset_bounds(e: np.ndarray, lit: np.ndarray, idx: np.ndarray, lo_ns: float, hi_ns: float,
                  rising: bool) -> tuple[int, float, float] | None:
    """The frame where `lit` switches (first rise or last fall in `idx` order) and the bounds it
    puts on the timing error delta = true exposure - estimated exposure."""
    contiguous = np.diff(idx) == 1
    if rising:
        j = np.flatnonzero(lit[1:] & ~lit[:-1] & contiguous)
        if j.size == 0:
            return None
        after, before = idx[j[0] + 1], idx[j[0]]
        # e_after + delta >= t_on >= lo, e_before + delta < t_on <= hi
        return int(after), lo_ns - e[after], hi_ns - e[before]
    j = np.flatnonzero(~lit[1:] & lit[:-1] & contiguous)
    if j.size == 0:
        return None
    last, nxt = idx[j[-1]], idx[j[-1] + 1]
    return int(last), lo_ns - e[nxt], hi_ns - e[last]


def optical_check(cameras: Sequence[CameraSync], flashes: Sequence[Flash], brightness: BrightnessFn, *,
                  t0_ns: int = 0, margin_frames: int = 4, min_contrast: float = 2.0,
                  progress: Progress = silent) -> dict:
    """Find each flash's onset (and end) in every camera's images and compare with the timestamps.

    Only frames within `margin_frames` of where the timestamps put the flash's edges are decoded.
    A frame counts as lit above halfway between the darkest and brightest of them (a bright flash
    over a dimmer set-point). The first lit frame bounds the camera's timing error delta (true minus
    timestamp-predicted exposure): e[first] + delta >= flash start and e[previous] + delta < flash
    start, with the flash start only known to lie between the command's send and acknowledgement;
    the end of the flash bounds it the same way. The bounds of all flashes are intersected.
    progress("optical check", cameras done, cameras) after each camera.
    """
    out: dict = {"flashes": [{"on_ms": round((f.on_ns - t0_ns) / 1e6, 4), "duration_ms": f.duration_ns / 1e6,
                              "on_uncertainty_ms": (f.on_hi_ns - f.on_lo_ns) / 1e6} for f in flashes],
                 "cameras": {}}
    for done, cam in enumerate(cameras, 1):
        e = cam.exposure_ns
        ok = np.flatnonzero(np.isfinite(e))
        entry: dict = {"flashes_seen": 0, "onset_frames": [], "exposure_error_ms": None, "consistent": None,
                       "measured_offset_ms": None, "predicted_offset_ms": None, "error_ms": None}
        out["cameras"][cam.id] = entry
        if ok.size < 2 or cam.fit is None:
            progress("optical check", done, len(cameras))
            continue
        period = max(cam.interval_mean_ns, 1.0) if np.isfinite(cam.interval_mean_ns) else 1e7
        margin = margin_frames + int(math.ceil(max((f.on_hi_ns - f.on_lo_ns) for f in flashes) / period)) \
            if flashes else margin_frames
        windows = []
        for f in flashes:
            k_on = int(np.searchsorted(e[ok], f.on_ns))
            k_off = int(np.searchsorted(e[ok], f.on_ns + f.duration_ns))
            sel = np.unique(np.clip(np.concatenate([np.arange(k_on - margin, k_on + margin + 1),
                                                    np.arange(k_off - margin, k_off + margin + 1)]),
                                    0, ok.size - 1))
            windows.append((k_on, ok[sel]))
        wanted = np.unique(np.concatenate([w for _, w in windows])) if windows else np.zeros(0, np.int64)
        values = np.asarray(brightness(cam.id, wanted), np.float64) if wanted.size else np.zeros(0)
        level = dict(zip(wanted.tolist(), values.tolist()))
        lo_delta, hi_delta = -math.inf, math.inf
        for f, (k_on, idx) in zip(flashes, windows):
            b = np.array([level[i] for i in idx.tolist()])
            if b.size < 3 or b.max() - b.min() < min_contrast:
                entry["onset_frames"].append({"predicted": int(ok[min(k_on, ok.size - 1)]), "measured": None})
                continue
            lit = b > (b.max() + b.min()) / 2
            rise = _onset_bounds(e, lit, idx, f.on_lo_ns, f.on_hi_ns, rising=True)
            fall = _onset_bounds(e, lit, idx, f.on_lo_ns + f.duration_ns, f.on_hi_ns + f.duration_ns,
                                 rising=False)
            entry["onset_frames"].append({"predicted": int(ok[min(k_on, ok.size - 1)]),
                                          "measured": None if rise is None else rise[0]})
            for bound in (rise, fall):
                if bound is not None:
                    lo_delta, hi_delta = max(lo_delta, bound[1]), min(hi_delta, bound[2])
            entry["flashes_seen"] += rise is not None
        if np.isfinite(lo_delta) and np.isfinite(hi_delta):
            entry["exposure_error_ms"] = [round(lo_delta / 1e6, 4), round(hi_delta / 1e6, 4)]
            entry["consistent"] = bool(lo_delta <= hi_delta)
            if entry["consistent"]:
                # zero inside the bounds: the timestamps agree with what the images show
                entry["error_ms"] = round(max(lo_delta, 0.0, -hi_delta) / 1e6, 4)
            if cam.fit.offset_ns is not None and entry["consistent"]:
                scale = 1.0 + cam.fit.drift_ppm * 1e-6
                # a later true exposure means a smaller device-minus-host offset
                entry["measured_offset_ms"] = [round((cam.fit.offset_ns - hi_delta * scale) / 1e6, 4),
                                               round((cam.fit.offset_ns - lo_delta * scale) / 1e6, 4)]
                entry["predicted_offset_ms"] = round(cam.fit.offset_ns / 1e6, 4)
        progress("optical check", done, len(cameras))
    return out
