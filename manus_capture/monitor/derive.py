"""From a source's cumulative counters to what the page shows: rates over the last second and alerts.

A source only counts (frames, drops, bytes written); the monitor keeps the snapshots of the last
second and derives, per camera, fps and bytes/s, and per take the disk write rate and the time
left at that rate. Alerts (the page's red banner):

- camera lost: its status is not "ok" (disconnected, stopped delivering, failed);
- drop burst: BURST_DROPS or more new drops (sequence gaps) within the last BURST_WINDOW_S (when
  samples lie further apart, the same rate: BURST_DROPS per BURST_WINDOW_S);
- disk low: free space under the rig's storage.min_free_gb;
- LEDs: the controller's status is not "ok" (lost or failed).

A source may give its own rates (a recorded take gives its means): a camera's "fps" or
"bytes_per_s" in the snapshot is kept as it is.
"""

from __future__ import annotations

import time
from collections import deque
from typing import Any

RATE_WINDOW_S = 1.0   # fps, bytes/s and the disk write rate are measured over this
BURST_DROPS = 5       # new drops within BURST_WINDOW_S that make a burst
BURST_WINDOW_S = 1.0


def _rate(now: float, then: float, dt: float) -> float | None:
    return None if dt <= 0 else max(0.0, (now - then) / dt)


def _alert(kind: str, message: str, camera: str | None = None) -> dict[str, Any]:
    return {"kind": kind, "camera": camera, "message": message}


class Deriver:
    """Snapshots of the last second in; the status JSON (snapshot + rates + alerts) out."""

    def __init__(self) -> None:
        self.history: deque[tuple[float, dict]] = deque()

    def add(self, snap: dict, t_s: float | None = None) -> dict:
        """The status for `snap`, taken at `t_s` (seconds, the snapshot's t_ns when it has one)."""
        if t_s is None:
            t_s = snap["t_ns"] / 1e9 if isinstance(snap.get("t_ns"), int) else time.monotonic()
        if self.history and self.history[-1][1].get("take") != snap.get("take"):
            self.history.clear()   # a new take counts from zero: no rate across two takes
        self.history.append((t_s, snap))
        # keep the newest snapshot at least RATE_WINDOW_S old: rates span a whole second once there is one
        while len(self.history) > 2 and t_s - self.history[1][0] >= RATE_WINDOW_S:
            self.history.popleft()
        return derive(snap, t_s, *self.history[0])


def derive(snap: dict, t_s: float, t_then: float, then: dict) -> dict:
    """The status JSON: `snap` with rates against the earlier snapshot `then` (taken at t_then) and alerts."""
    dt = t_s - t_then
    before = {c["id"]: c for c in then.get("cameras", [])}
    recording = snap.get("status") == "recording"
    cameras, alerts = [], []
    for cam in snap.get("cameras", []):
        old = before.get(cam["id"], cam)
        fps = cam.get("fps", _rate(cam.get("frames", 0), old.get("frames", 0), dt) if recording else None)
        rate = cam.get("bytes_per_s", _rate(cam.get("bytes", 0), old.get("bytes", 0), dt) if recording else None)
        cameras.append({**cam, "fps": fps, "bytes_per_s": rate})
        if cam.get("status", "ok") != "ok":
            alerts.append(_alert("camera_lost", f"camera {cam['id']}: {cam['status']}", cam["id"]))
        new_drops = (cam.get("drops") or 0) - (old.get("drops") or 0)
        if recording and new_drops >= BURST_DROPS * max(1.0, dt / BURST_WINDOW_S):
            alerts.append(_alert("drop_burst", f"camera {cam['id']}: {new_drops} frames dropped in "
                                 f"{max(dt, 0):.1f} s", cam["id"]))
    status = {**snap, "cameras": cameras, "disk": _disk(snap.get("disk"), then.get("disk"), dt, recording),
              "alerts": alerts}
    disk = status["disk"]
    if disk is not None and disk.get("low"):
        alerts.append(_alert("disk_low", f"disk {disk.get('path', '')}: {disk['free_bytes'] / 1e9:.2f} GB free, "
                             f"under storage.min_free_gb {disk['min_free_gb']:g} GB"))
    leds = snap.get("leds")
    if leds and leds.get("status", "ok") != "ok":
        alerts.append(_alert("leds", f"LED controller: {leds['status']}"))
    return status


def _disk(disk: dict | None, old: dict | None, dt: float, recording: bool) -> dict | None:
    """The disk panel: write rate over the window, time left at that rate before the free space
    reaches min_free_gb (where the recorder stops), and whether it already has."""
    if not disk:
        return None
    old = old or disk
    rate = _rate(disk.get("written_bytes", 0), old.get("written_bytes", 0), dt) if recording else None
    floor = disk.get("min_free_gb", 0.0) * 1e9
    free = disk.get("free_bytes")
    left = None if free is None or not rate else max(0.0, (free - floor) / rate)
    return {**disk, "write_bytes_per_s": rate, "time_left_s": left, "low": free is not None and free < floor}
