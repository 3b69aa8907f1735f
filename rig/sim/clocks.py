"""Timing of the simulated cameras: when each frame is exposed, what the device stamps on it,
when the host receives it, and whether it is lost on the way.

Everything is a closed-form function of (camera, frame number) plus seeded noise drawn in blocks,
so that any frame's timing can be asked for in any order and the ground truth is exact.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from manus_core.rig_config import SimCameraConfig

_BLOCK = 4096  # frames per noise block: noise of frame k depends only on (seed, camera, stream, k)
_STREAMS = {"ts_jitter": 1, "trigger": 2, "latency": 3, "drop": 4}


@lru_cache(maxsize=256)   # 8 MB: 53 cameras' four streams over 4096 frames
def _block(seed: int, cam: int, stream: str, block: int, kind: str) -> np.ndarray:
    # a camera asks for one frame at a time, and drawing its block anew for each frame cost 0.2 ms
    rng = np.random.default_rng([seed, cam, _STREAMS[stream], block])
    values = rng.standard_normal(_BLOCK) if kind == "normal" else (
        rng.standard_exponential(_BLOCK) if kind == "exponential" else rng.random(_BLOCK))
    values.flags.writeable = False
    return values


def _noise(seed: int, cam: int, stream: str, k: np.ndarray, kind: str) -> np.ndarray:
    k = np.asarray(k, dtype=np.int64)
    out = np.empty(k.shape, np.float64)
    for block in np.unique(k // _BLOCK):
        sel = (k // _BLOCK) == block
        out[sel] = _block(seed, cam, stream, int(block), kind)[k[sel] % _BLOCK]
    return out


@dataclass(frozen=True)
class CameraClock:
    """One camera's clock and transport model; times in ns on the host (reference) clock."""

    params: SimCameraConfig
    fps: float
    index: int
    seed: int
    t0_ns: int  # the take's nominal tick 0 on the host clock

    @property
    def period_ns(self) -> float:
        return 1e9 / self.fps

    def free_run_exposure_ns(self, k: np.ndarray) -> np.ndarray:
        """Mid-exposure of free-running frame k: the camera's own oscillator, off by drift."""
        p = self.params
        period = self.period_ns / (1 + p.drift_ppm * 1e-6)
        return self.t0_ns + p.phase_ms * 1e6 + np.asarray(k, np.float64) * period

    def triggered_exposure_ns(self, trigger_ns: np.ndarray, k: np.ndarray) -> np.ndarray:
        """Mid-exposure after a trigger sent at `trigger_ns` (software or hardware)."""
        p = self.params
        jitter = _noise(self.seed, self.index, "trigger", k, "normal") * p.trigger_jitter_us * 1e3
        return np.asarray(trigger_ns, np.float64) + p.trigger_latency_us * 1e3 + jitter

    def device_ns(self, exposure_ns: np.ndarray, k: np.ndarray) -> np.ndarray:
        """The device's timestamp: its clock reads host time plus an offset, running fast by drift."""
        p = self.params
        elapsed = np.asarray(exposure_ns, np.float64) - self.t0_ns
        jitter = _noise(self.seed, self.index, "ts_jitter", k, "normal") * p.timestamp_jitter_us * 1e3
        return np.rint(self.t0_ns + p.clock_offset_ms * 1e6 + elapsed * (1 + p.drift_ppm * 1e-6) + jitter).astype(np.int64)

    def host_ns(self, exposure_ns: np.ndarray, k: np.ndarray, exposure_us: float) -> np.ndarray:
        """Arrival at the host: half the exposure, readout and transfer, with a one-sided tail."""
        p = self.params
        tail = _noise(self.seed, self.index, "latency", k, "exponential") * p.latency_jitter_ms * 1e6
        return np.rint(np.asarray(exposure_ns, np.float64) + exposure_us * 500 + p.latency_ms * 1e6 + tail).astype(np.int64)

    def dropped(self, k: np.ndarray) -> np.ndarray:
        return _noise(self.seed, self.index, "drop", k, "uniform") < self.params.drop_rate
