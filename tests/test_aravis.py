"""The Aravis backend against real Aravis devices: the fake GigE Vision camera
(arv-fake-gv-camera-0.8) on 127.0.0.1 and in network namespaces, and the in-process Fake.

The fake GV camera speaks GVCP/GVSP over UDP exactly as a GigE camera does, so discovery,
feature access, streaming, frame ids (16-bit, wrapping), timestamps, software trigger and
loss of control are exercised through the real protocol stack.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import subprocess
import tempfile
import threading
import time

import numpy as np
import pytest
from click.testing import CliRunner

from manus_capture.commands.rig_list import list_command
from manus_core.errors import CameraDisconnected, CameraError
from manus_core.rig_config import CameraConfig
from rig.cameras import Camera
from rig.cameras.aravis import AravisCamera, FrameIdUnwrapper, list_aravis_cameras

try:
    from rig.cameras.aravis import aravis

    aravis()
    HAVE_ARAVIS = True
except CameraError:
    HAVE_ARAVIS = False

FAKE_GV = shutil.which("arv-fake-gv-camera-0.8")
needs_aravis = pytest.mark.skipif(not HAVE_ARAVIS, reason="Aravis 0.8 (gir1.2-aravis-0.8) not installed")
needs_fake_gv = pytest.mark.skipif(not (HAVE_ARAVIS and FAKE_GV),
                                   reason="arv-fake-gv-camera-0.8 not installed (apt: aravis-tools)")
GVCP_PORT = 3956


def test_frame_ids_unwrap_across_the_16_bit_wrap():
    unwrap = FrameIdUnwrapper()
    raw = [65533, 65534, 65535, 1, 2, 5, 4, 6]            # GigE Vision 1.x: 0 is skipped
    assert [unwrap(r) for r in raw] == [65533, 65534, 65535, 65536, 65537, 65540, 65539, 65541]
    wide = FrameIdUnwrapper()                              # 64-bit ids (GEV 2, USB3 Vision)
    assert [wide(r) for r in [65534, 65535, 65536, 70000]] == [65534, 65535, 65536, 70000]


@contextlib.contextmanager
def _fake_gv_lock():
    # One fake camera on 127.0.0.1:3956 at a time, also across pytest-xdist workers.
    with open(os.path.join(tempfile.gettempdir(), "manus-capture-fake-gv.lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


def _listening(pid: int) -> bool:
    # /proc/PID/net is the process's own network namespace.
    try:
        with open(f"/proc/{pid}/net/udp") as f:
            return any(line.split()[1].endswith(f":{GVCP_PORT:04X}") for line in list(f)[1:])
    except OSError:
        return False


@contextlib.contextmanager
def fake_gv_camera(serial: str, interface: str = "127.0.0.1", netns: str | None = None):
    cmd = [FAKE_GV, "-i", interface, "-s", serial]
    if netns:
        cmd = ["ip", "netns", "exec", netns, *cmd]      # ip execs the camera: same pid
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 10
        while not _listening(proc.pid):
            if proc.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"arv-fake-gv-camera-0.8 did not start on {interface} (exit {proc.poll()})")
            time.sleep(0.02)
        yield proc
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


@pytest.fixture()
def loopback_camera():
    with _fake_gv_lock(), fake_gv_camera(f"MC{os.getpid()}") as proc:
        yield proc


def _cfg(device: str, **kw) -> CameraConfig:
    base = dict(id="gv0", backend="aravis", device=device, width=320, height=240, fps=125.0,
                pixel_format="Mono8", exposure_us=1500.0, gain_db=3.0)
    return CameraConfig(**{**base, **kw})


@contextlib.contextmanager
def opened(cfg: CameraConfig, **kw):
    cam = AravisCamera(cfg, **kw)
    cam.open()
    try:
        cam.configure()
        yield cam
    finally:
        cam.close()


def _stream(cam: AravisCamera, n: int, deadline_s: float = 15.0) -> list:
    """Start and read until n frames have arrived. The deadline is generous: these tests are about
    what the frames carry, and a loaded machine only delays the fakes' wake-ups."""
    cam.start()
    frames, deadline = [], time.monotonic() + deadline_s
    while len(frames) < n and time.monotonic() < deadline:
        frame = cam.read(0.5)
        if frame is not None:
            frames.append(frame)
    return frames


def _check_stream(frames, cfg, t_before_ns, t_after_ns, rel=0.02):
    seq = np.array([f.seq for f in frames])
    t_dev = np.array([f.t_device_ns for f in frames])
    t_host = np.array([f.t_host_ns for f in frames])
    assert np.all(np.diff(seq) >= 1) and np.all(np.diff(t_dev) > 0)
    # The frame period from the camera's own clock. The fake stamps a frame when its thread
    # wakes up, so single intervals jitter (and stall on a loaded machine); the median does not.
    period = np.median(np.diff(t_dev) / np.diff(seq))
    assert period == pytest.approx(1e9 / cfg.fps, rel=rel)
    assert np.all((t_host >= t_before_ns) & (t_host <= t_after_ns)) and np.all(np.diff(t_host) > 0)
    for f in frames:
        assert (f.width, f.height, f.encoding, len(f.data)) == (cfg.width, cfg.height, "mono8",
                                                                cfg.width * cfg.height)
    return seq, t_dev


@needs_fake_gv
def test_loopback_camera_features_and_stream(loopback_camera):
    cfg = _cfg("127.0.0.1")
    with opened(cfg) as cam:
        assert isinstance(cam, Camera)
        got = cam.settings()
        assert got["region"] == (0, 0, 320, 240) and got["pixel_format"] == "Mono8"
        assert (got["fps"], got["exposure_us"], got["gain_db"]) == (125.0, 1500.0, 3.0)
        assert (got["trigger_mode"], got["tick_hz"]) == ("Off", 1_000_000_000)
        info = cam.info()
        assert (info.serial, info.model, info.can_trigger) == (f"MC{os.getpid()}", "Fake", True)
        t0 = time.clock_gettime_ns(time.CLOCK_MONOTONIC)
        frames = _stream(cam, 150)                     # the fake's ids start at 65401: this wraps
        t1 = time.clock_gettime_ns(time.CLOCK_MONOTONIC)
        assert len(frames) == 150
        seq, t_dev = _check_stream(frames, cfg, t0, t1)
        stats = cam.stats()
        cam.stop()
    assert seq[-1] > 65535
    assert stats["frames"] == len(frames) and stats["seq_gaps"] == seq[-1] - seq[0] + 1 - len(frames)
    assert {"n_missing_frames", "n_underruns", "n_missing_packets", "n_completed_buffers"} <= set(stats)


@needs_fake_gv
def test_software_trigger_gives_one_frame_per_trigger(loopback_camera):
    cfg = _cfg(f"MC{os.getpid()}", width=64, height=48, fps=50.0)     # opened by serial number
    with opened(cfg, sync="software-trigger") as cam:
        got = cam.settings()
        assert (got["trigger_mode"], got["trigger_source"]) == ("On", "Software")
        cam.start()
        assert cam.read(0.3) is None                   # nothing without a trigger
        frames = []
        for _ in range(5):
            cam.trigger()
            frames.append(cam.read(2.0))
        assert cam.read(0.3) is None                   # and nothing more
        cam.stop()
    seq = [f.seq for f in frames]
    assert seq == list(range(seq[0], seq[0] + 5))
    assert all(f.t_device_ns > 0 for f in frames)


@needs_fake_gv
def test_wrong_settings_are_named(loopback_camera):
    with pytest.raises(CameraError, match=r"gv0: pixel format 'MJPG' is not offered \(offers .*Mono8"):
        with opened(_cfg("127.0.0.1", pixel_format="MJPG")):
            pass
    with pytest.raises(CameraError, match="gv0: width 4096 is outside 1..2048"):
        with opened(_cfg("127.0.0.1", width=4096, height=4096)):
            pass
    with pytest.raises(CameraError, match="gv0: frame rate 5000 is outside 0.1..1000"):
        with opened(_cfg("127.0.0.1", fps=5000.0)):
            pass
    with pytest.raises(CameraError, match="'NO-SUCH-CAMERA' not found"):
        AravisCamera(_cfg("NO-SUCH-CAMERA")).open()
    with opened(_cfg("127.0.0.1")) as cam:
        with pytest.raises(CameraError, match="needs sync 'software-trigger'"):
            cam.trigger()


@needs_fake_gv
def test_camera_that_goes_away_is_reported():
    with _fake_gv_lock(), fake_gv_camera(f"MCLOST{os.getpid()}") as proc:
        with opened(_cfg("127.0.0.1", width=64, height=48, fps=50.0)) as cam:
            cam.start()
            assert cam.read(1.0) is not None
            proc.kill()
            proc.wait()
            with pytest.raises(CameraDisconnected, match="gv0 .*control lost"):
                for _ in range(40):                    # Aravis's heartbeat gives up after ~6 s
                    cam.read(0.5)


# -- several cameras, each in its own network namespace ------------------------------------------
def _run(*cmd: str) -> None:
    subprocess.run(cmd, check=True, capture_output=True, text=True)


@pytest.fixture()
def namespaced_cameras():
    """Three fake cameras, each behind a veth pair in a namespace of its own, as on a GigE switch."""
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root (CAP_NET_ADMIN)")
    tag = f"mc{os.getpid() % 100000}"
    spaces = [f"{tag}n{k}" for k in range(3)]
    created: list[str] = []
    with _fake_gv_lock(), contextlib.ExitStack() as stack:
        try:
            used = subprocess.run(["ip", "-o", "addr"], capture_output=True, text=True).stdout
            octet = next(o for o in range(213, 250) if f"10.{o}." not in used)
            for k, ns in enumerate(spaces):
                host, cam = f"{tag}h{k}", f"{tag}c{k}"
                _run("ip", "netns", "add", ns)
                created.append(ns)
                _run("ip", "link", "add", host, "type", "veth", "peer", "name", cam)
                _run("ip", "link", "set", cam, "netns", ns)
                _run("ip", "addr", "add", f"10.{octet}.{k}.1/24", "dev", host)
                _run("ip", "link", "set", host, "up")
                _run("ip", "netns", "exec", ns, "ip", "addr", "add", f"10.{octet}.{k}.2/24", "dev", cam)
                _run("ip", "netns", "exec", ns, "ip", "link", "set", cam, "up")
        except (subprocess.CalledProcessError, FileNotFoundError) as exc:
            for ns in created:
                subprocess.run(["ip", "netns", "del", ns], capture_output=True)
            detail = exc.stderr.strip() if isinstance(exc, subprocess.CalledProcessError) else str(exc)
            pytest.skip(f"cannot create network namespaces here: {detail}")
        # Deleting a namespace destroys its veth end, and with it the pair.
        for ns in created:
            stack.callback(subprocess.run, ["ip", "netns", "del", ns], capture_output=True)
        serials = []
        for k, ns in enumerate(spaces):
            serials.append(f"{tag.upper()}S{k}")
            stack.enter_context(fake_gv_camera(serials[-1], f"{tag}c{k}", netns=ns))
        yield serials, octet


@needs_fake_gv
def test_cameras_in_network_namespaces(namespaced_cameras):
    serials, octet = namespaced_cameras
    found = {c.serial: c for c in list_aravis_cameras()}
    for k, serial in enumerate(serials):
        assert found[serial].address == f"10.{octet}.{k}.2" and found[serial].protocol == "GigEVision"
    cfgs = [_cfg(serial, id=f"ns{k}", width=160, height=120, fps=50.0) for k, serial in enumerate(serials)]
    results: dict[str, list] = {}
    with contextlib.ExitStack() as stack:
        cams = [stack.enter_context(opened(cfg)) for cfg in cfgs]
        t0 = time.clock_gettime_ns(time.CLOCK_MONOTONIC)
        threads = [threading.Thread(target=lambda c=c: results.__setitem__(c.cfg.id, _stream(c, 40)))
                   for c in cams]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        t1 = time.clock_gettime_ns(time.CLOCK_MONOTONIC)
        assert sorted(c.info().serial for c in cams) == sorted(serials)
        for cam in cams:
            cam.stop()
    for cfg in cfgs:
        frames = results[cfg.id]
        assert len(frames) == 40, cfg.id
        # Three fakes share the CPU with the test: their wake-ups run late, not their clocks.
        _check_stream(frames, cfg, t0, t1, rel=0.05)


# -- Aravis's in-process fake camera --------------------------------------------------------------
@needs_aravis
def test_in_process_fake_camera():
    aravis().enable_interface("Fake")
    cfg = _cfg("Fake_1", width=64, height=48, fps=100.0, exposure_us=800.0, gain_db=1.0)
    with opened(cfg) as cam:
        got = cam.settings()
        assert got["region"] == (0, 0, 64, 48)
        assert (got["fps"], got["exposure_us"], got["gain_db"]) == (100.0, 800.0, 1.0)
        t0 = time.clock_gettime_ns(time.CLOCK_MONOTONIC)
        frames = _stream(cam, 30)
        t1 = time.clock_gettime_ns(time.CLOCK_MONOTONIC)
        stats = cam.stats()
        cam.stop()
    assert len(frames) == 30
    _check_stream(frames, cfg, t0, t1)
    assert stats["n_completed_buffers"] >= len(frames)


@needs_aravis
def test_rig_list_command_shows_the_fake_camera():
    result = CliRunner().invoke(list_command, ["--fake"])
    assert result.exit_code == 0, result.output
    assert "aravis  Fake_1" in result.output
    assert result.output.strip().splitlines()[-1].startswith("found ")
