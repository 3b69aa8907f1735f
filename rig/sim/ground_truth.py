"""ground_truth.h5 of a simulated take (DESIGN.md, "On disk"): everything later stages are scored on."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from manus_core.fileio import atomic_output

GZIP = {"compression": "gzip", "compression_opts": 4}


def default_label_frames(n_frames: int, count: int = 8) -> np.ndarray:
    """Evenly spaced frames to label, away from the first and last tick."""
    if n_frames <= 0:
        return np.zeros(0, np.int64)
    return np.unique(np.linspace(0, n_frames - 1, min(count, n_frames) + 2).round().astype(np.int64)[1:-1]) \
        if n_frames > 2 else np.arange(n_frames)


def _frame_table(cube) -> tuple[np.ndarray, np.ndarray]:
    """exposure_mid_ns (C,F) (-1 where a camera produced no frame for a tick) and dropped (C,F)."""
    n_ticks = 1 + max((r[0] for recs in cube.records for r in recs), default=-1)
    exposure = np.full((len(cube.records), n_ticks), -1, np.int64)
    dropped = np.zeros((len(cube.records), n_ticks), bool)
    for c, recs in enumerate(cube.records):
        if recs:
            arr = np.array(recs, dtype=np.int64)
            exposure[c, arr[:, 0]] = arr[:, 1]
            dropped[c, arr[:, 0]] = arr[:, 2].astype(bool)
    return exposure, dropped


def write_ground_truth(cube, path, label_frames=None) -> Path:
    """Write the truth of everything the cube's cameras produced so far, atomically."""
    path = Path(path)
    exposure, dropped = _frame_table(cube)
    n_ticks = exposure.shape[1]
    ticks = cube.tick_ns(np.arange(n_ticks))
    label_frames = default_label_frames(n_ticks) if label_frames is None else \
        np.asarray([f for f in label_frames if 0 <= f < n_ticks], np.int64)
    cams = cube.cameras
    with atomic_output(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs.update(kind=cube.kind, fps=cube.config.fps, sync=cube.config.sync, t0_ns=cube.t0_ns,
                       subject=cube.config.sim.subject, object=cube.config.sim.object,
                       paint=cube.config.sim.paint, seed=cube.config.sim.seed,
                       tags_json=json.dumps(cube.world.tags_json()))
        g = f.create_group("cameras")
        g["ids"] = np.array(cams.ids, dtype=h5py.string_dtype())
        for name in ("K", "dist", "R", "t", "size"):
            g[name] = getattr(cams, name)
        params = [c.sim for c in cube.camera_configs]
        g = f.create_group("clock")
        g["offset_ns"] = np.array([p.clock_offset_ms * 1e6 for p in params])
        g["drift_ppm"] = np.array([p.drift_ppm for p in params])
        g["phase_ns"] = np.array([p.phase_ms * 1e6 for p in params])
        g["latency_ns"] = np.array([p.latency_ms * 1e6 for p in params])
        g["trigger_latency_ns"] = np.array([p.trigger_latency_us * 1e3 for p in params])
        g = f.create_group("frames")
        g["tick_ns"] = ticks.round().astype(np.int64)
        g["exposure_mid_ns"] = exposure
        g["dropped"] = dropped
        g["led_level"] = np.array([cube.lighting(int(t)) for t in ticks], np.float32)
        seconds = cube.seconds(ticks)
        if cube.hand is not None:
            angles = cube.motion.hand_angles(seconds)
            g = f.create_group("hand")
            g["joint_angles"] = angles
            g["joints3d"] = cube.hand.skeleton.forward(angles)
            g["bone_lengths"] = cube.hand.skeleton.bone_lengths
            g = f.create_group("contact")
            g["points_rest"] = cube.hand.surface_rest
            g["bone"] = cube.hand.surface_bone
            if cube.kind == "grasp" and cube.object is not None:
                g.create_dataset("instant", data=cube.motion.contact_instant(seconds), **GZIP)
                g["accumulated"] = cube.motion.contact_accumulated()
            elif cube.kind == "canonical":
                g["accumulated"] = cube.motion.state(0.0).paint
        if cube.object is not None:
            R, t = cube.motion.object_poses(seconds)
            g = f.create_group("object")
            g.attrs["name"] = cube.object.name
            g["R"], g["t"] = R, t
        g = f.create_group("labels")
        g["frames"] = label_frames
        h, w = int(cams.size[:, 1].max()), int(cams.size[:, 0].max())
        # h5py cannot chunk an empty dataset: no labels asked for, a plain empty one
        chunked = dict(chunks=(1, 1, h, w), **GZIP) if len(label_frames) else {}
        images = g.create_dataset("image", shape=(len(cams), len(label_frames), h, w), dtype=np.uint8,
                                  **chunked)
        for c in range(len(cams)):
            for j, frame in enumerate(label_frames):
                t = exposure[c, frame] if exposure[c, frame] >= 0 else ticks[frame]
                lab = cube.render(c, float(t), labels=True).labels
                images[c, j, :lab.shape[0], :lab.shape[1]] = lab
    return path
