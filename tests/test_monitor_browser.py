"""The live monitor in a real browser: Debian's chromium, headless, driven by Selenium through
Debian's chromedriver (docs/setup.md, "The browser"), on the page of a simulated 12-camera take.

The take records in a thread of this process (so that a camera can be unplugged on cue through a
wrapped sim backend, as in test_recorder) and the monitor serves its live source as
`record --monitor` does. With MONITOR_SCREENSHOT=PATH the page is also saved as a PNG once the
banner is up, at a resolution that makes readable thumbnails (the picture in docs/recording.md):

    MONITOR_SCREENSHOT=docs/img/monitor.png .venv/bin/python -m pytest -q -p no:xdist tests/test_monitor_browser.py
"""

from __future__ import annotations

import dataclasses
import io
import os
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import pytest
from PIL import Image
from test_recorder import wrap_backend

from manus_capture.monitor import start_monitor
from manus_core.errors import CameraDisconnected
from rig.cameras import Frame
from rig.layouts import make_rig
from rig.record import LiveSession, RecordOptions, StopFlag, TakeResult, record_take

if TYPE_CHECKING:
    from selenium.webdriver import Chrome

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
SCREENSHOT = os.environ.get("MONITOR_SCREENSHOT")
CAMERAS = 12
# small and slow enough to record in real time beside the browser on two busy cores; the
# thumbnail is a 1/4-size decode (manus_capture/monitor/thumbs.py)
FPS = 10.0 if SCREENSHOT else 20.0
RESOLUTION = (256, 144) if SCREENSHOT else (64, 36)
WAIT_S = 15.0             # the longest any one thing the page should show may take to show


def browser() -> Chrome:
    """Headless chromium, both binaries by path: Selenium Manager never runs (no download)."""
    missing = [str(p) for p in (CHROMIUM, CHROMEDRIVER) if not p.is_file()]
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        missing.append("the selenium package")
    if missing:
        pytest.fail(f"the browser test needs {', '.join(missing)}: run `make setup` (installs Debian's "
                    "chromium and chromium-driver, and the dev extra with selenium)", pytrace=False)
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
                "--window-size=1280,600", "--no-first-run", "--disable-extensions"):
        options.add_argument(arg)
    return webdriver.Chrome(options=options, service=Service(executable_path=str(CHROMEDRIVER)))


class Unpluggable:
    """A camera that is unplugged when `unplug` is set: its next read raises CameraDisconnected."""

    def __init__(self, inner, unplug: threading.Event) -> None:
        self.inner, self.unplug = inner, unplug

    def read(self, timeout_s: float = 1.0) -> Frame | None:
        if self.unplug.is_set():
            raise CameraDisconnected("camera unplugged")
        return self.inner.read(timeout_s)

    def __getattr__(self, name):
        return getattr(self.inner, name)


@pytest.fixture
def live_take(tmp_path, monkeypatch) -> Iterator[tuple[str, str, threading.Event, Callable[[], TakeResult]]]:
    """A simulated 12-camera take recording in real time, served by the monitor: (page url, the
    camera that `unplug` unplugs, unplug, end() -> the take's result)."""
    rig = make_rig("cube53", cameras=CAMERAS, resolution=RESOLUTION, fps=FPS, seed=3)
    cams = tuple(dataclasses.replace(c, sim=dataclasses.replace(c.sim, drop_rate=0.0)) for c in rig.cameras)
    rig = dataclasses.replace(rig, cameras=cams, sim=dataclasses.replace(rig.sim, time_scale=1.0))
    lost = rig.cameras[4].id
    unplug = threading.Event()
    wrap_backend(monkeypatch, "sim", lambda cid, cam: Unpluggable(cam, unplug) if cid == lost else cam)
    session = tmp_path / "s"
    source = LiveSession(rig, session)
    server = start_monitor(source, "127.0.0.1", 0)
    stop = StopFlag()
    out: dict[str, TakeResult | BaseException] = {}

    def run() -> None:
        try:
            out["result"] = record_take(rig, session, "t", "calibration", 60.0, RecordOptions(use_leds=False),
                                        stop=stop, on_live=source.attach)
        except BaseException as exc:   # noqa: BLE001 - handed to the test's thread
            out["result"] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()

    def end() -> TakeResult:
        stop.set("the test has seen enough")
        thread.join(30)
        result = out.get("result")
        if isinstance(result, BaseException):
            raise result
        assert result is not None, "the take did not end within 30 s of the stop"
        return result

    try:
        yield server.url, lost, unplug, end
    finally:
        stop.set("test over")
        thread.join(30)
        server.stop()


PAGE_STATE = """
const cams = [...document.querySelectorAll('.cam')].map((el) => {
  const img = el.querySelector('img.thumb');
  let pixels = null;
  if (img.complete && img.naturalWidth) {
    const c = document.createElement('canvas');
    c.width = img.naturalWidth; c.height = img.naturalHeight;
    c.getContext('2d').drawImage(img, 0, 0);
    pixels = c.toDataURL();
  }
  return {id: el.dataset.camera, status: el.dataset.status, lost: el.classList.contains('lost'),
          frames: Number(el.querySelector('.frames').textContent), fps: Number(el.querySelector('.fps').textContent),
          loads: Number(img.dataset.loads),
          width: img.naturalWidth, height: img.naturalHeight, pixels: pixels};
});
const banner = document.getElementById('banner');
return {updates: Number(document.body.dataset.updates), cams: cams, banner: !banner.hidden,
        banner_text: banner.textContent, alerts: banner.dataset.alerts || ''};
"""


def wait_for(driver: Chrome, what: str, ok: Callable[[dict], bool]) -> dict:
    """The page's state once ok(state) holds; fails naming `what` and the last state after WAIT_S."""
    deadline = time.monotonic() + WAIT_S
    while True:
        state = driver.execute_script(PAGE_STATE)
        if ok(state):
            return state
        if time.monotonic() > deadline:
            brief = {k: v for k, v in state.items() if k != "cams"}
            brief["cams"] = [{k: v for k, v in c.items() if k != "pixels"} for c in state["cams"]]
            pytest.fail(f"the page did not show {what} within {WAIT_S:g} s; it shows {brief}")
        time.sleep(0.1)


def shown(state: dict) -> bool:
    """Every camera has a cell with a thumbnail on screen."""
    return len(state["cams"]) == CAMERAS and all(c["pixels"] for c in state["cams"])


def test_page_shows_the_take_live_and_the_banner_when_a_camera_is_unplugged(live_take):
    url, lost, unplug, end = live_take
    driver = browser()
    try:
        driver.get(url)
        first = wait_for(driver, f"all {CAMERAS} cameras with a thumbnail", shown)
        # a machine too busy to keep up may show drop bursts; a lost camera there is none
        assert "camera_lost" not in first["alerts"], first["banner_text"]
        assert all(c["status"] == "ok" and not c["lost"] for c in first["cams"])
        width, height = RESOLUTION
        assert {(c["width"], c["height"]) for c in first["cams"]} == {(-(-width // 4), -(-height // 4))}
        before = {c["id"]: c for c in first["cams"]}
        # every thumbnail is replaced by a new frame's (sensor noise differs frame to frame) and
        # every counter rises, pushed to the page
        later = wait_for(driver, "new thumbnails and higher frame counts for every camera", lambda s: shown(s) and all(
            c["loads"] > before[c["id"]]["loads"] and c["pixels"] != before[c["id"]]["pixels"]
            and c["frames"] > before[c["id"]]["frames"] for c in s["cams"]))
        assert later["updates"] > first["updates"] and "camera_lost" not in later["alerts"]
        unplug.set()
        alarmed = wait_for(driver, f"the banner for the unplugged camera {lost}",
                           lambda s: s["banner"] and "camera_lost" in s["alerts"].split())
        assert f"camera {lost}: disconnected" in alarmed["banner_text"]
        assert driver.find_element("id", "banner").is_displayed()
        cells = {c["id"]: c for c in alarmed["cams"]}
        assert cells[lost]["status"] == "disconnected" and cells[lost]["lost"]
        assert all(c["status"] == "ok" and not c["lost"] for cam, c in cells.items() if cam != lost)
        # the others go on recording while the banner is up
        going = wait_for(driver, "the other cameras' counters still rising", lambda s: all(
            c["frames"] > cells[c["id"]]["frames"] for c in s["cams"] if c["id"] != lost))
        frames_lost = {c["id"]: c["frames"] for c in going["cams"]}[lost]
        if SCREENSHOT:   # once the take caught up with its start; 128 colours: flat but for the thumbnails
            wait_for(driver, f"every camera at {FPS:g} FPS", lambda s: all(
                abs(c["fps"] - FPS) < 1 for c in s["cams"] if c["id"] != lost))
            shot = Image.open(io.BytesIO(driver.get_screenshot_as_png())).convert("RGB")
            shot.quantize(128, dither=Image.Dither.NONE).save(SCREENSHOT, optimize=True)
    finally:
        driver.quit()
    result = end()
    assert [c.id for c in result.lost] == [lost]
    stored = {c.id: c.frames for c in result.cameras}
    # what the page counted is what the take holds: the unplugged camera's count stopped there
    assert stored[lost] == frames_lost
    assert all(stored[cam] >= cells[cam]["frames"] for cam in stored)
