"""The web monitor: derived rates and alerts, thumbnails, the token, a port in use, requests that try
to leave the session, the server-sent events of a real uvicorn, and the page over a recorded take."""

from __future__ import annotations

import dataclasses
import json
import re
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request

import cv2
import numpy as np
import pytest
from starlette.testclient import TestClient

from dataset_tools.sync import sync_take
from manus_capture.monitor import RecordedSource, build_app, parse_address, start_monitor
from manus_capture.monitor.derive import BURST_DROPS, Deriver
from manus_capture.monitor.thumbs import Thumbnails, thumbnail
from manus_core.errors import MonitorError
from manus_core.take import Take
from rig.layouts import make_rig
from rig.record import RecordOptions, record_take

FPS = 120
STEP_S = 0.25


def gradient_jpeg(width: int = 640, height: int = 360, shade: int = 0) -> bytes:
    y, x = np.mgrid[0:height, 0:width]
    image = np.dstack([(x + shade) % 256, (y * 2) % 256, ((x ^ y) + shade) % 256]).astype(np.uint8)
    return cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()


class CountingSource:
    """A live source whose clock and counters advance by STEP_S at every snapshot: FPS frames a
    second per camera, `drops_per_step` new drops on camera c1."""

    def __init__(self, drops_per_step: int = 0, free_bytes: int = 50 * 10**9) -> None:
        self.ids = ["c0", "c1"]
        self.steps, self.drops_per_step, self.free_bytes = 0, drops_per_step, free_bytes
        self.lost: set[str] = set()
        self.jpeg = gradient_jpeg()

    def camera_ids(self) -> list[str]:
        return list(self.ids)

    def snapshot(self) -> dict:
        self.steps += 1
        t = self.steps * STEP_S
        frames = int(FPS * t)
        cams = [{"id": c, "frames": frames, "drops": self.drops_per_step * self.steps if c == "c1" else 0,
                 "bytes": frames * 1000, "buffer_fill": 0.1, "status": "disconnected" if c in self.lost else "ok",
                 "last_frame_ns": int(t * 1e9)} for c in self.ids]
        return {"take": "t1", "session": "s", "kind": "grasp", "status": "recording", "t_ns": int(t * 1e9),
                "elapsed_s": t, "duration_s": 10.0, "cameras": cams,
                "disk": {"path": "/data", "free_bytes": self.free_bytes, "written_bytes": 2 * frames * 1000,
                         "min_free_gb": 5.0},
                "leds": {"level": 0.5, "status": "ok", "flashes": 3}}

    def latest_jpeg(self, cam: str) -> bytes | None:
        if cam not in self.ids:
            raise KeyError(cam)
        return self.jpeg


def derived(source: CountingSource, samples: int) -> dict:
    deriver = Deriver()
    for _ in range(samples):
        status = deriver.add(source.snapshot())
    return status


def test_rates_are_measured_over_the_last_second():
    status = derived(CountingSource(), 8)   # 2 s of snapshots
    for cam in status["cameras"]:
        assert cam["fps"] == pytest.approx(FPS)
        assert cam["bytes_per_s"] == pytest.approx(FPS * 1000)
    disk = status["disk"]
    assert disk["write_bytes_per_s"] == pytest.approx(2 * FPS * 1000)
    assert disk["time_left_s"] == pytest.approx((50e9 - 5e9) / (2 * FPS * 1000))
    assert status["alerts"] == []


def test_alerts_a_drop_burst_a_lost_camera_and_a_low_disk_but_not_a_trickle_of_drops():
    steps_per_s = round(1 / STEP_S)
    trickle = derived(CountingSource(drops_per_step=1), 8)       # 4 drops a second: no burst
    assert BURST_DROPS > steps_per_s and trickle["alerts"] == []
    burst = derived(CountingSource(drops_per_step=2), 8)         # 8 drops a second
    assert [(a["kind"], a["camera"]) for a in burst["alerts"]] == [("drop_burst", "c1")]
    source = CountingSource(free_bytes=4 * 10**9)
    source.lost.add("c0")
    kinds = {a["kind"]: a for a in derived(source, 2)["alerts"]}
    assert set(kinds) == {"camera_lost", "disk_low"}
    assert kinds["camera_lost"]["camera"] == "c0" and "disconnected" in kinds["camera_lost"]["message"]


def test_thumbnails_keep_to_their_cpu_budget():
    thumbs = Thumbnails(budget=0.25)
    first, second = gradient_jpeg(), gradient_jpeg(shade=60)
    shown = thumbs.get("c0", first)
    thumbs._cost_s = 0.5                  # as if a decode took 0.5 s: one per 2 s within a quarter core
    assert thumbs.get("c0", second) == shown and thumbs.decodes == 1   # the fresh one is shown again
    thumbs._made["c0"] -= 3.0             # 3 s later
    assert thumbs.get("c0", second) != shown and thumbs.decodes == 2
    unlimited = Thumbnails(budget=None)   # recorded takes: every frame asked for is decoded
    unlimited.get("c0", first)
    unlimited._cost_s = 0.5
    assert unlimited.get("c0", second) != shown and unlimited.decodes == 2


def test_status_thumbnails_and_unknown_cameras_through_the_app():
    source = CountingSource()
    app, monitor = build_app(source)
    with TestClient(app) as client:
        deadline = time.monotonic() + 5
        while (status := client.get("/api/status").json()).get("elapsed_s", 0) < 1.5:
            assert time.monotonic() < deadline, status
            time.sleep(0.05)
        assert [c["id"] for c in status["cameras"]] == ["c0", "c1"]
        for cam in status["cameras"]:
            assert {"frames", "fps", "drops", "buffer_fill", "status", "bytes_per_s"} <= set(cam)
            assert cam["fps"] == pytest.approx(FPS)
        assert status["leds"]["flashes"] == 3 and status["disk"]["min_free_gb"] == 5.0

        page = client.get("/")
        assert page.status_code == 200 and 'id="banner"' in page.text
        assert "://" not in page.text   # no CDN: the page loads nothing from elsewhere

        thumbs = [client.get(f"/api/cameras/c0/latest.jpg?n={i}") for i in range(3)]
        assert all(r.status_code == 200 and r.headers["content-type"] == "image/jpeg" for r in thumbs)
        small = cv2.imdecode(np.frombuffer(thumbs[0].content, np.uint8), cv2.IMREAD_COLOR)
        assert small.shape == (90, 160, 3) and len(thumbs[0].content) < len(source.jpeg)
        assert monitor.thumbs.decodes == 1      # three polls of one frame: one decode
        source.jpeg = gradient_jpeg(shade=60)
        deadline = time.monotonic() + 2   # a new frame shows once the CPU budget allows its decode
        while client.get("/api/cameras/c0/latest.jpg").content == thumbs[0].content:
            assert time.monotonic() < deadline
            time.sleep(0.02)
        assert monitor.thumbs.decodes == 2

        missing = client.get("/api/cameras/nope/latest.jpg")
        assert missing.status_code == 404 and missing.json()["cameras"] == ["c0", "c1"]
        for attempt in ("/api/cameras/..%2F..%2Fetc/latest.jpg", "/api/cameras/..%2F..%2Fetc%2Fpasswd/latest.jpg",
                        "/api/cameras/%2Fetc%2Fpasswd/latest.jpg", "/..%2F..%2Fetc%2Fpasswd"):
            refused = client.get(attempt)
            assert refused.status_code == 404 and b"root:" not in refused.content, attempt
        assert client.post("/api/status").status_code == 405   # read-only

        source.snapshot = lambda: 1 / 0   # a source that fails is reported; the monitor goes on
        time.sleep(0.4)
        failing = client.get("/api/status").json()
        assert "ZeroDivisionError" in failing["source_error"] and failing["take"] == "t1"


def get(url: str, **headers: str) -> int:
    """The HTTP status of a GET to a real server."""
    try:
        with urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=5) as answer:
            return answer.status
    except urllib.error.HTTPError as exc:
        return exc.code


def test_a_token_is_required_off_loopback_and_events_stream_from_a_real_server():
    source = CountingSource()
    server = start_monitor(source, "0.0.0.0", 0)
    try:
        assert server.token_generated and server.token and f"token={server.token}" in server.url
        base = f"http://127.0.0.1:{server.port}"
        assert get(f"{base}/api/status") == 401 and get(f"{base}/") == 401
        assert get(f"{base}/api/status?token=wrong") == 401
        assert get(f"{base}/api/status", **{"X-Monitor-Token": server.token}) == 200
        assert get(f"{base}/?token={server.token}") == 200
        events = []
        with urllib.request.urlopen(f"{base}/api/events?token={server.token}", timeout=5) as stream:
            assert stream.headers["content-type"].startswith("text/event-stream")
            while len(events) < 3:
                line = stream.readline().decode()
                if line.startswith("data: "):
                    events.append(json.loads(line[6:]))
            server.stop()   # a page still connected does not keep the server from stopping
            assert not server.running and server.error is None
        assert len({e["t_ns"] for e in events}) >= 2   # pushed as the source advances
        assert all(e["take"] == "t1" and len(e["cameras"]) == 2 for e in events)
    finally:
        server.stop()


def test_a_port_in_use_is_one_error_naming_it(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(MonitorError, match=rf"port {port} on 127\.0\.0\.1 is in use"):
            start_monitor(CountingSource(), "127.0.0.1", port)
        (tmp_path / "take").mkdir()
        (tmp_path / "take" / "take.json").write_text(json.dumps({"cameras": ["c0"]}))
        res = subprocess.run([sys.executable, "-m", "manus_capture.cli", "monitor", str(tmp_path / "take"),
                              "--port", str(port)], capture_output=True, text=True, timeout=60)
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip().count("\n") == 0 and f"port {port}" in res.stderr and "Traceback" not in res.stderr
    with pytest.raises(MonitorError, match="expected \\[HOST:\\]PORT"):
        parse_address("localhost:http")
    assert parse_address("8000") == ("127.0.0.1", 8000) and parse_address("[::1]:9") == ("::1", 9)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """A 0.3 s take of 3 cameras at 64x36 on the simulated rig, with its sync report."""
    rig = make_rig("cube53", cameras=3, resolution=(64, 36), fps=60.0, seed=4)
    rig = dataclasses.replace(rig, sim=dataclasses.replace(rig.sim, supersample=1))
    folder = tmp_path_factory.mktemp("monitor") / "s"
    record_take(rig, folder, "t1", "calibration", 0.3, RecordOptions(use_leds=False))
    sync_take(folder / "t1")
    return folder


def test_the_recorded_session_shows_frames_by_index_verdicts_and_the_timeline(session):
    source = RecordedSource(session)
    take = Take(session / "t1")
    cams = list(take.cameras)
    app, _ = build_app(source)
    with TestClient(app) as client:
        status = client.get("/api/status").json()
        assert status["review"]["takes"][0]["name"] == "t1"
        verdict = json.loads((session / "t1" / "sync_report.json").read_text())["verdict"]
        assert status["review"]["takes"][0]["verdict"] == verdict == status["verdict"]
        assert [c["id"] for c in status["cameras"]] == cams
        assert [c["frames"] for c in status["cameras"]] == [take.frame_count(c) for c in cams]

        packet = [p for _, p in zip(range(3), take.packets(cams[1]))][2].tobytes()
        shown = client.get(f"/api/cameras/{cams[1]}/latest.jpg", params={"take": "t1", "frame": 2})
        assert shown.status_code == 200 and shown.content == thumbnail(packet)
        beyond = client.get(f"/api/cameras/{cams[1]}/latest.jpg", params={"frame": take.frame_count(cams[1])})
        assert beyond.status_code == 204

        png = client.get("/api/timeline.png", params={"take": "t1"})
        assert png.status_code == 200 and png.content.startswith(b"\x89PNG")
        for bad in ("../../etc", "..", "/etc/passwd"):
            refused = client.get("/api/status", params={"take": bad})
            assert refused.status_code == 404 and refused.json()["takes"] == ["t1"], bad
        unknown = client.get("/api/cameras/../latest.jpg", params={"take": "t1"})
        assert unknown.status_code == 404
    take_only = RecordedSource(session / "t1")
    assert list(take_only.takes) == ["t1"] and take_only.snapshot()["session"] == "s"


def test_monitor_command_refuses_a_folder_that_is_no_take(tmp_path):
    res = subprocess.run([sys.executable, "-m", "manus_capture.cli", "monitor", str(tmp_path), "--port", "0"],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and str(tmp_path) in res.stderr and "Traceback" not in res.stderr


def test_a_path_that_is_no_take_or_session_says_which(tmp_path):
    (tmp_path / "frames.csv").write_text("")
    (tmp_path / "empty").mkdir()
    for path, words in ((tmp_path / "nope", "no such take or session folder"),
                        (tmp_path / "frames.csv", "a file, not a take or session folder"),
                        (tmp_path / "empty", "neither a take (no take.json) nor a session")):
        with pytest.raises(MonitorError, match="^" + re.escape(f"{path}: {words}")):
            RecordedSource(path)
