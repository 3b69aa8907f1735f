"""ground_truth.h5 of a simulated take (manus_core.ground_truth: the layout and its reader):
everything later stages are scored on."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from manus_core.fileio import atomic_output
from manus_core.ground_truth import (
    GZIP,
    LABEL_FRAMES,
    LABEL_IMAGE,
    TruthCameras,
    TruthClock,
    TruthContact,
    TruthFrames,
    TruthHand,
    TruthInfo,
    TruthObject,
    TruthSkin,
    write_record,
)
from rig.sim.hand import subject_toml


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
    sim = cube.config.sim
    params = [c.sim for c in cube.camera_configs]
    with atomic_output(path) as tmp, h5py.File(tmp, "w") as f:
        write_record(f, TruthInfo(cube.kind, cube.config.fps, cube.config.sync, cube.t0_ns, sim.subject, sim.object,
                                  sim.paint, sim.seed, json.dumps(cube.world.tags_json())))
        write_record(f, TruthCameras(cams.ids, cams.K, cams.dist, cams.R, cams.t, cams.size))
        write_record(f, TruthClock(np.array([p.clock_offset_ms * 1e6 for p in params]),
                                   np.array([p.drift_ppm for p in params]),
                                   np.array([p.phase_ms * 1e6 for p in params]),
                                   np.array([p.latency_ms * 1e6 for p in params]),
                                   np.array([p.trigger_latency_us * 1e3 for p in params])))
        write_record(f, TruthFrames(ticks.round().astype(np.int64), exposure, dropped,
                                    np.array([cube.lighting(int(t)) for t in ticks], np.float32)))
        seconds = cube.seconds(ticks)
        if cube.hand is not None:
            angles = cube.motion.hand_angles(seconds)
            hand = cube.hand
            write_record(f, TruthHand(angles, hand.skeleton.forward(angles), hand.skeleton.bone_lengths,
                                      hand.skeleton.rest_joints()))
            write_record(f, TruthSkin(hand.surface_rest, hand.surface_normal_rest, hand.surface_bone, hand.faces,
                                      hand.weights, subject_toml(hand.shape)),
                         compressed=("points", "normals", "bone", "faces", "weights"))
            instant = accumulated = None
            if cube.kind == "grasp" and cube.object is not None:
                instant, accumulated = cube.motion.contact_instant(seconds), cube.motion.contact_accumulated()
            elif cube.kind == "canonical":
                accumulated = cube.motion.state(0.0).paint
            write_record(f, TruthContact(cube.hand.surface_rest, cube.hand.surface_bone, instant, accumulated),
                         compressed=("instant",))
        if cube.object is not None:
            write_record(f, TruthObject(cube.object.name, *cube.motion.object_poses(seconds)))
        f[LABEL_FRAMES] = label_frames
        h, w = int(cams.size[:, 1].max()), int(cams.size[:, 0].max())
        # h5py cannot chunk an empty dataset: no labels asked for, a plain empty one
        chunked = dict(chunks=(1, 1, h, w), **GZIP) if len(label_frames) else {}
        images = f.create_dataset(LABEL_IMAGE, shape=(len(cams), len(label_frames), h, w), dtype=np.uint8, **chunked)
        for c in range(len(cams)):
            for j, frame in enumerate(label_frames):
                t = exposure[c, frame] if exposure[c, frame] >= 0 else ticks[frame]
                lab = cube.render(c, float(t), labels=True).labels
                images[c, j, :lab.shape[0], :lab.shape[1]] = lab
    return path
