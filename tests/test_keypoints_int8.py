"""`models quantize mediapipe-hand`: the full landmark model in int8, calibrated on a take.

It is calibrated on the small rendered take of test_annotate_detect (simulated hands) and judged on
what it was not calibrated on: MMPose's real hand photos (the float model's PCK floors) and the
rendered hands' true joints (as near as the float model's keypoints). The cache is a folder of this
test's, holding links to the installed models, so the user's cache is left as it was.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from test_annotate_detect import CAMERAS, TICKS, installed, rendered  # noqa: F401  (fixtures)
from test_keypoints_real import FLOORS, gt_box, pck_hits, samples  # noqa: F401  (fixture)
from test_keypoints_take import make_take

from dataset_tools.keypoints import hand_keypoint_detector
from dataset_tools.keypoints.install import bundle_dir
from dataset_tools.keypoints.keypoints2d import detect_take
from manus_capture.cli import cli
from manus_core.take import Take


@pytest.fixture(scope="module")
def cache(tmp_path_factory, installed) -> Path:  # noqa: F811
    """XDG_CACHE_HOME for the module: the installed models linked in, no int8 model yet."""
    root = tmp_path_factory.mktemp("cache")
    models = root / "manus-capture" / "models" / "mediapipe-hand"
    models.mkdir(parents=True)
    for f in bundle_dir("mediapipe-hand").iterdir():
        if f.suffix in (".onnx", ".json") and "int8" not in f.name:
            (models / f.name).symlink_to(f)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("XDG_CACHE_HOME", str(root))
        yield models


@pytest.fixture(scope="module")
def quantized(cache, rendered) -> dict:  # noqa: F811
    """Before quantizing, the int8 model is refused with the command that makes it; then the command runs."""
    missing = CliRunner().invoke(cli, ["detect", str(rendered["take"]), "--model", "mediapipe-hand-int8",
                                       "--device", "cpu", "-o", str(rendered["root"] / "none.h5")])
    result = CliRunner().invoke(cli, ["models", "quantize", "mediapipe-hand", "--calibration",
                                      str(rendered["take"])])
    return {"missing": missing, "result": result}


def test_int8_is_asked_for_by_name_until_it_is_made(quantized) -> None:
    missing = quantized["missing"]
    assert missing.exit_code == 2, missing.output
    last = missing.output.strip().splitlines()[-1]
    assert "manus-capture models quantize mediapipe-hand --calibration TAKE" in last, last
    assert "Traceback" not in missing.output


def test_quantize_writes_the_model_and_what_it_was_calibrated_on(cache, quantized) -> None:
    result = quantized["result"]
    assert result.exit_code == 0, result.output
    assert f"calibrated on {len(CAMERAS) * len(TICKS)} hand crops of 1 take(s)" in result.output, result.output
    record = json.loads((cache / "int8.json").read_text())
    assert record["crops"] == len(CAMERAS) * len(TICKS) and record["source"] == "hand_landmark_full.onnx"
    # int8 weights: a quarter of the float file's size, give or take the quantization parameters
    sizes = [(cache / f"{stem}.onnx").stat().st_size for stem in ("hand_landmark_int8", "hand_landmark_full")]
    assert sizes[0] < 0.4 * sizes[1], sizes
    assert not [f for f in os.listdir(cache) if f.startswith(".")]      # nothing staged is left behind


def test_a_calibration_take_without_hands_is_refused_in_one_line(cache, tmp_path) -> None:
    """Frames without a hand (the empty cube) cannot calibrate anything: exit 2, the model untouched."""
    rng = np.random.default_rng(0)
    make_take(tmp_path / "empty", {"c0": [rng.integers(0, 256, (96, 128, 3), dtype=np.uint8) for _ in range(4)]})
    before = sorted(os.listdir(cache))
    result = CliRunner().invoke(cli, ["models", "quantize", "mediapipe-hand", "--calibration", str(tmp_path / "empty")])
    assert result.exit_code == 2, result.output
    assert "no hand found in the 4 frames looked at for calibration" in result.output.strip().splitlines()[-1]
    assert sorted(os.listdir(cache)) == before


def test_int8_keeps_the_float_models_floors_on_real_photos(quantized, samples) -> None:  # noqa: F811
    """Calibrated on rendered hands, scored on photographed ones: the float model's PCK floors hold
    (measured: float 0.82/1.00/0.92/0.78; int8 calibrated on this take's 15 crops 0.82/1.00/0.93/0.79)."""
    assert quantized["result"].exit_code == 0, quantized["result"].output
    det = hand_keypoint_detector("mediapipe-hand-int8", device="cpu")
    assert det.name == "mediapipe-hand-int8"
    for name, items in samples.items():
        boxes = [gt_box(k)[None] for _, k in items]
        found = det.detect_many([im for im, _ in items], boxes)
        pck = float(np.mean(np.concatenate([pck_hits(kp[0], k, b[0]) for (_, k), b, kp in zip(items, boxes, found)])))
        assert pck >= FLOORS[name], f"int8 on {name}: PCK@0.2 {pck:.3f} < {FLOORS[name]}"


def test_int8_tracks_the_rendered_hands_as_the_float_model_does(quantized, rendered) -> None:  # noqa: F811
    assert quantized["result"].exit_code == 0, quantized["result"].output
    take, rig, truth = Take(rendered["take"]), rendered["rig"], rendered["joints"]
    projected = rig.project(truth.reshape(-1, 3)).reshape(len(CAMERAS), len(TICKS), 21, 2)
    errors = {}
    for model in ("mediapipe-hand", "mediapipe-hand-int8"):
        found = detect_take(take, hand_keypoint_detector(model, device="cpu"))
        kp = np.stack([found[cam].keypoints for cam in CAMERAS]).astype(np.float64)
        assert (kp[:, :, 0, 2] > 0.5).all(), (model, kp[:, :, 0, 2])
        errors[model] = float(np.median(np.linalg.norm(kp[..., :2] - projected, axis=-1)))
    # measured: median 2.870 px float, 2.876 px int8
    assert errors["mediapipe-hand-int8"] < 1.25 * errors["mediapipe-hand"], errors
