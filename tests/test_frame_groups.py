"""Frame groups are made once per take, with the settings of the sync report the user checked, saved
beside it (frame_groups.npz) and read by every later stage (dataset_tools.sync.frame_groups)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dataset_tools.sync import GROUPS_FILE, frame_groups, sync_take
from manus_core.errors import SyncError
from manus_core.frames_csv import HEADER, format_row

FPS = 120.0
PERIOD_NS = 1e9 / FPS


def write_take(root: Path, cameras: int = 4, ticks: int = 240, seed: int = 0) -> Path:
    """take.json and frames.csv of hardware-triggered cameras: exposures on the tick (20 us of
    timestamp noise), device clocks offset by up to 5 ms, 1.5-3 ms transfer latency plus jitter."""
    rng = np.random.default_rng(seed)
    tick_ns = 10**9 + np.arange(ticks) * PERIOD_NS
    rows, cams = [HEADER + "\n"], []
    for c in range(cameras):
        offset, latency = rng.uniform(-5e6, 5e6), rng.uniform(1.5e6, 3e6)
        exposure = tick_ns + rng.normal(0, 2e4, ticks)
        host = exposure + latency + rng.exponential(2e5, ticks)
        rows += [format_row(f"c{c}", k, int(exposure[k] + offset), int(host[k]), 1000, 0) for k in range(ticks)]
        # the latency floor: half the 1 ms exposure plus latency_ms
        cams.append({"id": f"c{c}", "exposure_us": 1000, "latency_ms": (latency - 5e5) / 1e6})
    root.mkdir(parents=True)
    (root / "frames.csv").write_text("".join(rows))
    (root / "take.json").write_text(json.dumps({"kind": "grasp", "cameras": cams, "fps": FPS,
                                                "sync": "hardware-trigger", "t0_ns": 10**9, "status": "complete"}))
    return root


def test_later_stages_get_the_groups_the_report_measured(tmp_path: Path) -> None:
    """Without a report the same analysis computes the groups (and writes nothing); with one, the
    groups it saved, with its settings, are what every stage gets; a changed frames.csv is refused."""
    take = write_take(tmp_path / "take")
    computed = frame_groups(take)
    assert computed.path is None and computed.description == "sync (fitted device clocks), computed"
    assert not (take / GROUPS_FILE).exists()
    np.testing.assert_array_equal(computed.frame_index, np.tile(np.arange(240)[:, None], (1, 4)))
    # a latency floor given to the report moves its exposures, and so its groups' ticks
    report = sync_take(take, latency_ns={"c0": 6e6})
    saved = frame_groups(take)
    assert report["frame_groups"] == GROUPS_FILE and saved.path == take / GROUPS_FILE
    assert saved.description == "sync (fitted device clocks), frame_groups.npz of the sync report"
    assert saved.settings["latency_ns"]["c0"] == 6e6 and len(saved.frame_ns) == report["groups"]
    shift = saved.frame_ns - computed.frame_ns
    assert np.ptp(shift) <= 1 and abs(shift[0]) > 0.3e6
    np.testing.assert_array_equal(saved.frame_index, computed.frame_index)
    # frames.csv changed after the report: the saved groups index other rows now
    csv = (take / "frames.csv").read_text()
    (take / "frames.csv").write_text(csv + csv.splitlines()[-1] + "\n")
    with pytest.raises(SyncError, match=r"frame_groups.npz: made from another frames.csv"):
        frame_groups(take)
    (take / "frames.csv").write_text(csv)
    assert frame_groups(take).path == take / GROUPS_FILE
    (take / GROUPS_FILE).write_bytes(b"not a zip")
    with pytest.raises(SyncError, match="not a frame-groups file"):
        frame_groups(take)


def test_host_time_grouping_puts_each_tick_in_one_group(tmp_path: Path) -> None:
    """Takes the sync analysis refuses (here an unknown sync mode, then no fps) are grouped on host
    arrival times by the same grouping: free-running cameras with phases over 6 ms, 1.5-3 ms
    latency and jitter, drops."""
    rng = np.random.default_rng(3)
    rows = [HEADER + "\n"]
    expected = np.full((100, 4), -1)
    for c in range(4):
        phase, latency = rng.uniform(0, 6e6), rng.uniform(1.5e6, 3e6)
        index = 0
        for k in range(100):
            if (c, k) in {(1, 10), (2, 50), (2, 51)}:
                continue
            host = 5 * 10**9 + k * PERIOD_NS + phase + latency + rng.exponential(2e5)
            rows.append(format_row(f"c{c}", k, 0, int(host), 1, ""))
            expected[k, c] = index
            index += 1
    (tmp_path / "frames.csv").write_text("".join(rows))
    meta = {"kind": "grasp", "cameras": ["c0", "c1", "c2", "c3"], "fps": 120, "sync": "genlock"}
    (tmp_path / "take.json").write_text(json.dumps(meta))
    groups = frame_groups(tmp_path)
    assert groups.description == "host-time rounding (frames.csv), computed"
    np.testing.assert_array_equal(groups.frame_index, expected)
    np.testing.assert_allclose(np.diff(groups.frame_ns), PERIOD_NS, atol=1)
    # without fps the frame rate is measured from the arrivals
    (tmp_path / "take.json").write_text(json.dumps({**meta, "fps": None}))
    np.testing.assert_array_equal(frame_groups(tmp_path).frame_index, expected)
