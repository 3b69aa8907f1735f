"""LED controllers over real pseudo-terminals: the ASCII client against the simulated
controller (normal use, unplug/replug, line noise, silence, reboot), DMX framing against the
Enttec widget API byte for byte, a DMX widget on a pty, and the `leds` command."""

from __future__ import annotations

import os
import select
import threading
import time
from collections.abc import Callable

import numpy as np
import pytest
import serial
from click.testing import CliRunner

from manus_capture.cli import cli
from manus_core.errors import LedDisconnected, LedError, LedRejected, LedStaleReply, LedTimeout, LedValueError
from manus_core.rig_config import LedConfig
from rig.leds import AsciiLedController, Backoff, DmxLedController, SimulatedLedController, now_ns, open_led_controller
from rig.leds.dmx import EnttecParser, get_parameters_message, parse_parameters, send_dmx_message
from rig.leds.protocol import FrameParser, crc16, encode
from rig.leds.sim import VirtualPort

# Timeouts generous enough for a loaded machine, so that "answered at the first attempt" holds.
FAST = dict(timeout_s=0.25, retries=2, backoff=Backoff(initial_s=0.02, max_s=0.1, give_up_s=3.0))


def wait_until(condition: Callable[[], object], what: str, timeout_s: float = 5.0) -> None:
    """Poll `condition` until it holds; the deadline is generous, reaching it is a failure."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"gave up after {timeout_s:g} s waiting for {what}")
        time.sleep(0.001)


def plugging_back_opener(plug: Callable[[], None], failed: list[int]):
    """pyserial's opener, except that an open that fails (the device is out) notes its time and
    plugs the device back in: the next reconnect attempt finds it, whatever the machine's load."""
    def opener(*args, **kwargs):
        try:
            return serial.Serial(*args, **kwargs)
        except OSError:
            failed.append(now_ns())
            plug()
            raise
    return opener


@pytest.fixture()
def sim():
    with SimulatedLedController(panels=4) as device:
        yield device


@pytest.fixture()
def leds(sim):
    with AsciiLedController(sim.path, panels=4, level=0.8, **FAST) as client:
        yield client


# -- protocol --------------------------------------------------------------------------------
def test_crc_is_ccitt_false():
    assert crc16(b"123456789") == 0x29B1          # the catalogued check value of CRC-16/CCITT-FALSE
    assert encode(7, "SET", 2, 500) == b"$7,SET,2,500*%04X\n" % crc16(b"7,SET,2,500")


def test_parser_keeps_only_whole_valid_frames_across_noise():
    good = [encode(1, "OK", 10), encode(2, "OK", 20, "levels=1/2"), encode(0, "BOOT", 5)]
    corrupt = bytearray(encode(3, "OK", 30))
    corrupt[3] ^= 0x04                                    # a flipped bit: checksum fails
    stream = (b"\x00\xff noise " + good[0] + b"$9,OK,1" + good[1] + bytes(corrupt)
              + b"*12\n\r\n" + good[2])
    parser = FrameParser()
    got = []
    for i in range(len(stream)):                          # byte by byte: every split position
        got += parser.feed(stream[i:i + 1])
    assert [(m.seq, m.verb, m.args) for m in got] == [(1, "OK", ("10",)), (2, "OK", ("20", "levels=1/2")),
                                                      (0, "BOOT", ("5",))]
    assert parser.stats.torn_frames == 1 and parser.stats.bad_frames == 1
    assert parser.stats.garbage_bytes == len(b"\x00\xff noise ") + len(b"*12\n\r\n")


# -- normal use ------------------------------------------------------------------------------
def test_levels_flash_status_and_log(sim, leds):
    t0 = now_ns()
    leds.on()                                             # the configured level, 0.8
    leds.set_panel(2, 0.25)
    assert leds.status()["levels"] == [0.8, 0.8, 0.25, 0.8]
    flash = leds.flash(40, level=1.0)
    [(start, end, level)] = sim.flashes()
    assert (end - start, level) == (40_000_000, 1.0)                 # timed by the controller's clock
    # Off well after the flash, so that the check at onset + 45 ms below sees the set-point.
    wait_until(lambda: now_ns() > end + 10_000_000, "10 ms past the end of the flash")
    leds.off()
    t1 = now_ns()
    grid = np.arange(t0, t1, 100_000)                     # the panels every 0.1 ms
    state = sim.state_at(grid)
    lit = np.all(state == 1.0, axis=1)
    assert lit.sum() * 0.1 == pytest.approx(40.0, abs=0.2)
    onset = grid[np.argmax(lit)]                          # within 0.1 ms after the flash began
    assert flash["t_send_ns"] <= onset and onset - 100_000 < flash["t_ack_ns"]   # the ack brackets it
    assert np.array_equal(sim.state_at(onset - 200_000), [0.8, 0.8, 0.25, 0.8])
    assert np.array_equal(sim.state_at(onset + 45_000_000), [0.8, 0.8, 0.25, 0.8])
    assert np.array_equal(sim.state_at(t1), [0, 0, 0, 0])
    assert np.array_equal(sim.state_at(t0 - 1), [0, 0, 0, 0])

    records = leds.records()
    assert [r["cmd"] for r in records] == ["LVL", "LVL", "STAT", "FLASH", "LVL"]
    assert [r["seq"] for r in records] == [2, 3, 4, 5, 6]                # 1 was the session's HELLO
    assert all(r["status"] == "ok" and r["attempts"] == 1 and r["t_send_ns"] < r["t_ack_ns"] for r in records)
    assert records[3]["args"] == [40, 1000]
    us = [r["controller_t_us"] for r in records]
    assert us == sorted(us)


def test_trigger_pulses(sim, leds):
    ack = leds.trigger(500.0, count=20)
    wait_until(lambda: len(sim.pulse_times()[0]) >= 20, "20 trigger pulses")
    ids, times = sim.pulse_times()
    assert list(ids) == list(range(20))
    assert np.all(np.diff(times) == 2_000_000)                        # 500 Hz
    assert int(ack["reply"]["p0"]) == 0
    assert ack["t_send_ns"] <= times[0] <= ack["t_ack_ns"]
    status = leds.status()
    assert status["pulses"] == 20 and status["trigger_hz"] == 0.0     # the run is over
    second = leds.trigger(1000.0)                                     # until stopped
    wait_until(lambda: len(sim.pulse_times()[0]) >= 30, "10 pulses of the second run")
    leds.stop_trigger()
    assert int(second["reply"]["p0"]) == 20                           # ids keep counting
    ids, times = sim.pulse_times()
    assert list(ids) == list(range(len(ids))) and len(ids) >= 30
    assert np.all(np.diff(times[20:]) == 1_000_000)                   # 1000 Hz
    status = leds.status()
    assert status["pulses"] == len(ids) and status["trigger_hz"] == 0.0   # stopped


def test_bad_values_are_refused_before_sending(leds):
    with pytest.raises(LedValueError, match="panel 4 does not exist"):
        leds.set_panel(4, 0.5)
    with pytest.raises(LedValueError, match="outside 0..1"):
        leds.on(1.5)
    assert LedValueError.exit_code == 2 and leds.records() == []


def test_controller_refusal_is_an_error(sim):
    """A client configured for 6 panels talking to a 4-panel controller."""
    with AsciiLedController(sim.path, panels=6, **FAST) as leds:
        with pytest.raises(LedRejected, match="LVL .*refused: BADARG"):
            leds.on(0.5)
        assert leds.records()[-1]["status"] == "error"


# -- faults ----------------------------------------------------------------------------------
def test_unplug_and_replug_restores_the_set_point(sim):
    failed: list[int] = []
    with AsciiLedController(sim.path, panels=4, opener=plugging_back_opener(sim.replug, failed),
                            **FAST) as leds:
        leds.set_levels([0.7, 0.6, 0.5, 0.4])
        sim.unplug()
        record = leds.set_panel(0, 0.1)                   # blocks through the reconnect
    assert record["status"] == "ok" and record["attempts"] == 1
    assert np.array_equal(sim.state_at(record["t_ack_ns"]), [0.1, 0.6, 0.5, 0.4])
    assert len(failed) == 1 and np.array_equal(sim.state_at(failed[0]), [0, 0, 0, 0])   # dark while out
    events = [r for r in leds.records() if r.get("event") == "reconnect"]
    # Found at the second attempt, after the first backoff wait.
    assert len(events) == 1 and events[0]["attempts"] == 2 and events[0]["downtime_ms"] >= 20
    reapplied = [r for r in leds.records() if r.get("why") == "reconnect"]
    assert len(reapplied) == 1 and reapplied[0]["args"] == [700, 600, 500, 400]
    # The old set-point came back before the new command: the first level after replug is it.
    executed = sim.executed()
    assert [v for _, v in executed[-2:]] == ["LVL", "LVL"]


def test_unplugged_for_good_gives_a_clear_error(sim):
    with AsciiLedController(sim.path, panels=4, timeout_s=0.1, retries=1,
                            backoff=Backoff(initial_s=0.02, max_s=0.05, give_up_s=0.3)) as leds:
        leds.on()
        sim.unplug()
        with pytest.raises(LedDisconnected, match=r"ttyLEDSIM: disconnected .* not back after 0.3 s.*"
                                                  r"; LVL \(seq 3\) not acknowledged"):
            leds.off()
        *_, command, event = leds.records()
        assert event["event"] == "disconnected"
        # the command that failed says so, with its error, rather than staying pending
        assert command["cmd"] == "LVL" and command["status"] == "disconnected"
        assert command["error"].startswith(f"LED controller on {sim.path}: disconnected")


def test_noise_torn_and_corrupted_replies(sim, leds):
    sim.inject(b"\x00garbage$17,OK,99*0000\n$5,OK,1")    # junk, a bad frame, a torn one
    sim.fragment_replies = True
    assert leds.on(0.5)["attempts"] == 1
    sim.fragment_replies = False
    sim.corrupt_replies = 1                               # the ack of the flash is hit by noise
    record = leds.flash(20)
    # the resent flash is answered from the cache, flagged so: its own earlier reply, accepted
    assert record["attempts"] == 2 and record["status"] == "ok" and record["reply"] == {"cached": "1"}
    sim.drop_requests = 1                                 # the next request is lost on the way
    assert leds.set_panel(1, 0.3)["attempts"] == 2
    # Retried with the same sequence number: the flash ran once, not twice.
    verbs = [v for _, v in sim.executed()]
    assert verbs == ["HELLO", "LVL", "FLASH", "LVL"]


def test_controller_side_resynchronizes_after_host_noise(sim):
    with serial.Serial(sim.path, 115200, timeout=0.5) as port:
        port.write(b"\xff\xfe junk $12,ALL,5" + encode(3, "ALL", 250) + b"$4,ALL,1*ZZZZ\n")
        reply = port.readline()
    assert FrameParser().feed(reply)[0].seq == 3
    assert np.array_equal(sim.state_at(now_ns()), [0.25] * 4)
    assert sim.parser_stats.torn_frames == 1 and sim.parser_stats.bad_frames == 1


def test_silent_controller_times_out_then_recovers(sim):
    with AsciiLedController(sim.path, panels=4, timeout_s=0.1, retries=2) as leds:
        leds.on()
        sim.mute = True
        with pytest.raises(LedTimeout, match=r"no answer to FLASH \(seq 3\) after 3 attempts of 0.1 s"):
            leds.flash(10)
        assert leds.records()[-1]["status"] == "timeout"
        sim.mute = False
        assert leds.off()["status"] == "ok"
    assert [v for _, v in sim.executed()] == ["HELLO", "LVL", "LVL"]      # the unanswered flash never ran


def test_reboot_is_noticed_and_set_point_restored(sim, leds):
    leds.on(0.4)
    sim.reboot()
    assert np.array_equal(sim.state_at(now_ns()), [0, 0, 0, 0])
    # The BOOT announcement crosses the pty asynchronously: poll until it has been read.
    wait_until(lambda: leds.poll() or any(r.get("event") == "boot" for r in leds.records()), "BOOT")
    assert np.array_equal(sim.state_at(now_ns()), [0.4] * 4)
    assert [r.get("event") or r.get("why") for r in leds.records()[-2:]] == ["boot", "reboot"]


# -- sessions: one controller, one connection after another -----------------------------------
def test_each_connection_is_a_session_of_its_own(sim):
    with AsciiLedController(sim.path, panels=4, **FAST) as first:
        first.on(0.5)
        first.flash(10)
    with AsciiLedController(sim.path, panels=4, **FAST) as second:
        # numbered from 1 again, so its commands have the first connection's numbers ...
        assert second.levels == (0.5,) * 4                # ... and it starts from the panels as they are
        second.set_panel(1, 0.2)
        second.flash(10)
    assert first.session["nonce"] != second.session["nonce"]
    assert [r["seq"] for r in first.records()] == [r["seq"] for r in second.records()] == [2, 3]
    # ... and every one of them was carried out, not answered from the first one's replies
    assert [v for _, v in sim.executed()] == ["HELLO", "LVL", "FLASH", "HELLO", "LVL", "FLASH"]
    assert len(sim.flashes()) == 2
    after = sim.flashes()[-1][1]
    assert np.array_equal(sim.state_at(after), [0.5, 0.2, 0.5, 0.5])


def test_stale_replies_of_an_earlier_connection_are_skipped(sim):
    # replies that an earlier process never read, still in the port's buffer
    sim.inject(encode(1, "OK", 99, "nonce=7", "levels=1000/1000/1000/1000") + encode(2, "OK", 100))
    with AsciiLedController(sim.path, panels=4, **FAST) as leds:
        assert leds.levels == (0.0,) * 4                  # the HELLO reply with its own nonce, not the stale one
        record = leds.on(0.5)
    assert record["controller_t_us"] != 100 and np.array_equal(sim.state_at(now_ns()), [0.5] * 4)


@pytest.mark.parametrize("fault, why", [("hello_keeps_cache", "a reply the controller kept for an earlier request"),
                                        ("unflagged_cache", r"a reply from controller time \d+ µs, before")])
def test_a_reply_that_cannot_be_the_commands_own_is_refused(sim, fault, why):
    """Firmware that keeps its reply cache across HELLO: the host notices instead of trusting it."""
    sim.hello_keeps_cache = True
    setattr(sim, fault, True)
    with AsciiLedController(sim.path, panels=4, **FAST) as first:
        first.on(0.5)
    with AsciiLedController(sim.path, panels=4, **FAST) as second:
        with pytest.raises(LedStaleReply, match=rf"ttyLEDSIM: LVL \(seq 2\) was answered with {why}.*not carried out"):
            second.off()
        assert second.records()[-1]["status"] == "stale"
    assert np.array_equal(sim.state_at(now_ns()), [0.5] * 4)
    assert LedStaleReply.exit_code == 1


def test_firmware_without_sessions_is_refused(sim):
    sim.no_hello = True
    with pytest.raises(LedError, match=r"ttyLEDSIM: refused HELLO, so its firmware predates sessions"):
        AsciiLedController(sim.path, panels=4, **FAST)
    sim.no_hello = False
    with AsciiLedController(sim.path, panels=4, **FAST) as leds:   # the refused one let go of the port
        leds.on()


def test_open_led_controller_for_each_protocol(tmp_path):
    with open_led_controller(LedConfig(port="sim", protocol="sim", panels=3, level=0.5), **FAST) as leds:
        leds.on()
        assert np.array_equal(leds.sim.state_at(now_ns()), [0.5] * 3)
    with pytest.raises(LedError, match="cannot open"):
        open_led_controller(LedConfig(port=str(tmp_path / "ttyACM9"), protocol="ascii"))


# -- DMX -------------------------------------------------------------------------------------
def test_dmx_framing_byte_for_byte():
    # Label 6: 7E, label, length LSB/MSB (start code + slots), start code 0, slots, E7.
    msg = send_dmx_message(bytes([255, 128, 0, 7]))
    assert msg == bytes([0x7E, 0x06, 25, 0x00, 0x00, 255, 128, 0, 7] + [0] * 20 + [0xE7])
    full = send_dmx_message(bytes(range(256)) * 2)
    assert full[:5] == bytes([0x7E, 0x06, 0x01, 0x02, 0x00]) and full[5:-1] == bytes(range(256)) * 2
    assert full[-1] == 0xE7 and len(full) == 518
    with pytest.raises(ValueError):
        send_dmx_message(bytes(513))
    assert get_parameters_message() == bytes([0x7E, 0x03, 0x02, 0x00, 0x00, 0x00, 0xE7])
    params = parse_parameters(bytes([0x44, 0x01, 9, 1, 40]))
    assert params == {"firmware": 0x0144, "break_us": 96.03, "mab_us": 10.67, "rate_hz": 40}
    parser = EnttecParser()
    chunks = [b"\x01\x02" + msg[:7], msg[7:] + bytes([0x7E, 0x06, 0xFF, 0xFF]), get_parameters_message()]
    got = [m for c in chunks for m in parser.feed(c)]
    assert [label for label, _ in got] == [6, 3] and got[0][1] == msg[4:-1]


class FakeWidget:
    """An Enttec-compatible widget on a VirtualPort: records universes, answers label 3."""

    def __init__(self, path):
        self.port = VirtualPort(path)
        self.port.plug()
        # Unplugging while the thread polls the old fd would keep the pty alive until the poll
        # returns, and swallow a write that should fail; the lock keeps the two apart.
        self.lock = threading.Lock()
        self.universes: list[tuple[int, bytes]] = []
        self._received = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        parser = EnttecParser()
        while not self._stop.is_set():
            with self.lock:
                fd = self.port.master
                data = os.read(fd, 4096) if fd is not None and select.select([fd], [], [], 0.01)[0] else b""
            if not data:
                time.sleep(0.002)                  # lets plug/unplug take the lock between polls
                continue
            for label, payload in parser.feed(data):
                if label == 6:
                    with self._received:
                        self.universes.append((now_ns(), payload))
                        self._received.notify_all()
                elif label == 3:
                    os.write(fd, bytes([0x7E, 3, 5, 0, 0x44, 0x01, 9, 1, 40, 0xE7]))

    def wait_universes(self, n: int, timeout_s: float = 5.0) -> None:
        with self._received:
            if not self._received.wait_for(lambda: len(self.universes) >= n, timeout_s):
                pytest.fail(f"the widget got {len(self.universes)} DMX universes in {timeout_s:g} s, "
                            f"expected {n}")

    def plug(self):
        with self.lock:
            self.port.plug()

    def unplug(self):
        with self.lock:
            self.port.unplug()

    def close(self):
        self._stop.set()
        self._thread.join()
        self.port.unplug()


def test_dmx_controller_on_a_widget(tmp_path):
    widget = FakeWidget(str(tmp_path / "ttyUSB-dmx"))
    failed: list[int] = []
    try:
        with DmxLedController(widget.port.path, panels=3, start_channel=2,
                              opener=plugging_back_opener(widget.plug, failed), **FAST) as dmx:
            dmx.set_levels([1.0, 0.5, 0.0])
            assert dmx.status()["rate_hz"] == 40
            dmx.flash(30)
            widget.wait_universes(3)                       # the set-point, the flash, its end
            with pytest.raises(LedError, match="no trigger output"):
                dmx.trigger(120)
            widget.unplug()
            dmx.set_panel(2, 0.2)                          # reconnects, then sends
            widget.wait_universes(5)
        frames = [payload for _, payload in widget.universes]
        setpoint = bytes([0, 0, 255, 128, 0]) + bytes(20)
        assert len(frames) == 5 and len(failed) == 1
        assert frames[0] == setpoint                       # start code, ch1 unused, ch2..4 panels
        assert frames[1] == bytes([0, 0, 255, 255, 255]) + bytes(20)     # flash
        assert frames[2] == setpoint                       # restored by the host's timer
        assert frames[3] == setpoint                       # re-sent after the replug
        assert frames[4] == bytes([0, 0, 255, 128, 51]) + bytes(20)
        records = dmx.records()
        # The interrupted command is logged when issued; the set-point re-sent on reconnect after it.
        assert [r.get("cmd") or r.get("event") for r in records] == ["DMX", "FLASH", "FLASH-END", "DMX",
                                                                     "reconnect", "DMX"]
        assert records[2]["t_send_ns"] - records[1]["t_done_ns"] >= 30_000_000   # the flash lasted 30 ms
        assert records[3]["status"] == "sent" and records[5]["why"] == "reconnect"
        assert records[3]["t_done_ns"] > records[5]["t_send_ns"]
    finally:
        widget.close()


# -- command line ----------------------------------------------------------------------------
RIG = """
[rig]
name = "bench"
[[cameras]]
id = "c0"
backend = "v4l2"
device = "/dev/v4l/by-id/none"
"""


def test_leds_command(tmp_path):
    rig = tmp_path / "rig.toml"
    rig.write_text(RIG + '[leds]\nport = "sim"\nprotocol = "sim"\npanels = 2\nlevel = 0.6\n')
    runner = CliRunner()
    for args, expect in [(["on"], "2 panels at 0.60"), (["set", "0.3", "--panel", "1"], "panel 1 at 0.30"),
                         (["flash", "20"], "flashed 2 panels for 20 ms"), (["off"], "2 panels off"),
                         (["status"], "levels 0.00 0.00")]:
        result = runner.invoke(cli, ["leds", *args, "--rig", str(rig)])
        assert result.exit_code == 0, result.output
        assert expect in result.output
    bare = tmp_path / "bare.toml"
    bare.write_text(RIG)
    result = runner.invoke(cli, ["leds", "on", "--rig", str(bare)])
    assert result.exit_code == 2 and "bare.toml: leds: missing" in result.output
    result = runner.invoke(cli, ["leds", "set", "1.5", "--rig", str(rig)])
    assert result.exit_code == 2
