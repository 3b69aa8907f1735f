"""The monitor over recorded data: a take folder, or a whole session, reviewed after the fact.

Every name a request carries (a take, a camera) is looked up among the takes found when the
source was opened and the cameras of their take.json; a name that is not one of them is refused
before any path is made from it, so no request reaches a file outside the session.
"""

from __future__ import annotations

import itertools
import json
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from dataset_tools.sync.takes import REPORT_FILE
from manus_core.errors import MonitorError
from manus_core.session import load_session
from manus_core.take import Take

TIMELINE_FILE = "sync_timeline.png"


def _read_json(path: Path, cache: dict[Path, tuple[tuple[int, int], dict | None]]) -> dict | None:
    """A JSON file's content (None when missing or unreadable), read again only after it changed."""
    try:
        stat = path.stat()
    except OSError:
        return None
    key = (stat.st_mtime_ns, stat.st_size)
    if path not in cache or cache[path][0] != key:
        try:
            doc = json.loads(path.read_text())
        except (OSError, ValueError):
            doc = None
        cache[path] = (key, doc if isinstance(doc, dict) else None)
    return cache[path][1]


class RecordedTake:
    """One recorded take as a MonitorSource; its frames by index (a camera's k-th frames.csv row)."""

    def __init__(self, path: Path, session: str) -> None:
        self.take = Take(path)
        self.name, self.session = path.name, session
        self._json: dict[Path, tuple[tuple[int, int], dict | None]] = {}
        self._counts: dict[str, tuple[int, int, int | None]] | None = None
        self._readers: dict[str, tuple[int, Iterator[np.ndarray]]] = {}   # next frame index, open reader
        self._last: dict[str, tuple[int, bytes | None]] = {}
        self._locks = {cam: threading.Lock() for cam in self.take.cameras}

    def camera_ids(self) -> list[str]:
        return list(self.take.cameras)

    def report(self) -> dict | None:
        """sync_report.json, when sync-report (or the recorder's check) wrote one."""
        return _read_json(self.take.path / REPORT_FILE, self._json)

    def counts(self) -> dict[str, tuple[int, int, int | None]]:
        """Per camera (frames, bytes, host time of the last frame), from frames.csv."""
        if self._counts is None:
            rows = self.take.frames
            ids, index = np.unique(rows["cam"], return_inverse=True)
            frames = np.bincount(index, minlength=len(ids))
            nbytes = np.bincount(index, weights=rows["bytes"], minlength=len(ids))
            last = np.full(len(ids), np.iinfo(np.int64).min)
            np.maximum.at(last, index, rows["t_host_ns"])
            found = {str(c): (int(f), int(b), int(t)) for c, f, b, t in zip(ids, frames, nbytes, last)}
            self._counts = {cam: found.get(cam, (0, 0, None)) for cam in self.take.cameras}
        return self._counts

    def snapshot(self) -> dict:
        meta = self.take.meta
        report = self.report() or {}
        stats = report.get("cameras") or {}
        entries = {str(c.get("id")): c for c in meta["cameras"] if isinstance(c, dict)}
        start, stop = meta.get("start_ns"), meta.get("stop_ns")
        elapsed = (stop - start) / 1e9 if isinstance(start, int) and isinstance(stop, int) else meta.get("duration_s")
        cameras = []
        for cam, (frames, nbytes, last) in self.counts().items():
            entry = entries.get(cam, {})
            drops = (stats.get(cam) or {}).get("frames_dropped", entry.get("seq_gaps"))
            cameras.append({"id": cam, "frames": frames, "drops": drops, "bytes": nbytes, "buffer_fill": None,
                            "status": entry.get("status", "ok"), "last_frame_ns": last,
                            "fps": frames / elapsed if elapsed else None,
                            "bytes_per_s": nbytes / elapsed if elapsed else None})
        leds = meta.get("leds")
        return {"take": self.name, "session": self.session, "kind": meta.get("kind", ""),
                "status": meta.get("status", ""), "t_ns": None, "elapsed_s": elapsed,
                "duration_s": meta.get("duration_s"), "cameras": cameras, "disk": None,
                "leds": None if not isinstance(leds, dict) else {
                    "level": leds.get("level"), "status": leds.get("status", "ok"),
                    "flashes": len(meta.get("flashes") or [])},
                "verdict": report.get("verdict"), "reasons": report.get("reasons", []),
                "timeline": (self.take.path / TIMELINE_FILE).is_file()}

    def _check(self, cam: str) -> None:
        if cam not in self.take.cameras:
            raise KeyError(cam)

    def frame_jpeg(self, cam: str, k: int) -> bytes | None:
        """The JPEG bytes of frame index k of `cam` (None outside the take); KeyError for an unknown camera.

        Frames are read as packets, undecoded; a reader stays open per camera, so stepping forward
        (a slider, playback) reads on from where the last request stopped."""
        self._check(cam)
        if not 0 <= k < self.counts()[cam][0]:
            return None
        with self._locks[cam]:
            last = self._last.get(cam)
            if last is not None and last[0] == k:
                return last[1]
            at, packets = self._readers.get(cam, (0, None))
            if packets is None or k < at:
                at, packets = 0, self.take.packets(cam)
            packet = next(itertools.islice(packets, k - at, None), None)
            self._readers[cam] = (k + 1, packets)
            jpeg = None if packet is None else packet.tobytes()
            self._last[cam] = (k, jpeg)
        return jpeg

    def latest_jpeg(self, cam: str) -> bytes | None:
        """A recorded take's first frame (the page asks for others by index)."""
        return self.frame_jpeg(cam, 0)

    def timeline_png(self) -> bytes | None:
        """The sync timeline sync-report drew, when there is one."""
        path = self.take.path / TIMELINE_FILE
        return path.read_bytes() if path.is_file() else None


class RecordedSource:
    """A take folder or a session folder (its takes in session.toml's order, then any others).

    As a MonitorSource it shows its first take; `take(name)` gives each of them."""

    def __init__(self, path: str | Path) -> None:
        folder = Path(path)
        if (folder / "take.json").is_file():
            found = [folder]
        elif folder.is_dir():
            session = load_session(folder)
            order = {t["name"]: i for i, t in enumerate(session.takes)} if session else {}
            found = sorted((p for p in folder.iterdir() if (p / "take.json").is_file()),
                           key=lambda p: (order.get(p.name, len(order)), p.name))
        elif folder.exists():
            raise MonitorError(f"{folder}: a file, not a take or session folder")
        else:
            raise MonitorError(f"{folder}: no such take or session folder")
        if not found:
            raise MonitorError(f"{folder}: neither a take (no take.json) nor a session (no take folders in it)")
        self.path = folder
        self.takes = {p.name: RecordedTake(p, p.parent.name if p is folder else folder.name) for p in found}

    def take(self, name: str | None) -> RecordedTake:
        """Take `name` (the first when None); KeyError for a name that is not one of the takes."""
        return next(iter(self.takes.values())) if name is None else self.takes[name]

    def summary(self) -> list[dict]:
        """Each take: name, kind, status, verdict, cameras, duration (the page's take list)."""
        out = []
        for name, rec in self.takes.items():
            meta, report = rec.take.meta, rec.report() or {}
            out.append({"name": name, "kind": meta.get("kind", ""), "status": meta.get("status", ""),
                        "verdict": report.get("verdict"), "cameras": len(rec.take.cameras),
                        "duration_s": meta.get("duration_s")})
        return out

    def camera_ids(self) -> list[str]:
        return self.take(None).camera_ids()

    def snapshot(self) -> dict:
        return self.take(None).snapshot()

    def latest_jpeg(self, cam: str) -> bytes | None:
        return self.take(None).latest_jpeg(cam)
