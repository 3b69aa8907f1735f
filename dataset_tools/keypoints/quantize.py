"""MediaPipe's full hand landmark network in int8, calibrated on a lab's own takes.

`quantize_landmarks(takes)` finds hands with the float model and the palm detector in frames spread
over the takes' cameras and frames, crops them as the tracker does, and quantizes the network
statically with onnxruntime: QDQ, int8 weights per output channel, uint8 activations whose ranges
are the minimum and maximum each tensor reached on those crops. On an AVX-512 VNNI core it runs in
0.6 of the float model's time (docs/keypoints.md has the accuracy against the float model).

Calibrating on the lab's own recordings, as TensorRT's int8 calibration does, gives the ranges of
the lab's hands, light and cameras. The result is `hand_landmark_int8.onnx` beside the
installed models, with `int8.json` (what it was calibrated on, and how far its keypoints are from
the float model's on the calibration crops); `--model mediapipe-hand-int8` uses it.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from itertools import islice
from pathlib import Path

import numpy as np
import onnx
import onnxruntime.quantization as ortq
from onnx import version_converter

from manus_core.errors import ModelError
from manus_core.fileio import write_atomic
from manus_core.progress import Progress, silent
from manus_core.take import Take

from . import boxes as bx
from .detector import Detector, hand_keypoint_detector
from .install import model_path
from .models import MediaPipeHand

RECORD = "int8.json"
QDQ_OPSET = 13           # per-channel DequantizeLinear needs its `axis`, added in opset 13
CALIBRATION_BATCH = 4    # crops per calibration run: the range-recording model holds every activation
# The first convolutions stay in float. Quantized, they moved the hand presence by up to 0.2 (the
# tracker loses a hand below 0.5: 3 % of a tracked take's crops) and the keypoints by 1.5 px median
# in the crop; with the first 8 in float, 0.04 and 0.5 px, at 4.9 against 8.5 ms a crop in float
# (all quantized: 4.3 ms). Measured on 320 tracked crops of benchmarks/bench_stages.py's hand take.
FLOAT_CONVS = 8


def calibration_crops(takes: Sequence[Take], detector: Detector, crops: int = 64, min_score: float = 0.5,
                      progress: Progress = silent) -> np.ndarray:
    """(N,224,224,3) BGR crops of the hands that the float model finds, N <= `crops`, from frames
    spread evenly over every camera of the takes (twice as many frames looked at as crops wanted:
    some show no hand). Each crop is the one the tracker would take around the keypoints."""
    views = [(take, cam) for take in takes for cam in take.cameras if take.readable_frames(cam)]
    if not views:
        raise ModelError("no frames to calibrate on: the takes have no readable frames")
    per_view = max(1, -(-2 * crops // len(views)))
    size = detector.model.crop.width
    found: list[np.ndarray] = []
    looked = 0
    for i, (take, cam) in enumerate(views):
        progress("calibration cameras", i, len(views))
        n = take.readable_frames(cam)
        images = [image for _, image in islice(take.iter_frames(cam, 0, n, max(1, n // per_view)), per_view)]
        looked += len(images)
        for image, kp in zip(images, detector.find_hands(images, 1, min_score)):
            if len(kp) and kp[0, 0, 2] >= min_score:
                found.append(bx.crop(image, bx.rects_from_keypoints(kp[:1]), size, size)[0])
    progress("calibration cameras", len(views), len(views))
    if not found:
        raise ModelError(f"no hand found in the {looked} frames looked at for calibration: "
                         "give takes in which the cameras see a hand")
    step = max(1, len(found) // crops)
    return np.concatenate(found[::step][:crops])


def quantize_landmarks(takes: Sequence[Take], crops: int = 64, device: str = "cpu",
                       progress: Progress = silent) -> dict:
    """Quantize the full landmark model on crops of the takes' hands; returns what int8.json records."""
    detector = hand_keypoint_detector("mediapipe-hand", device=device)
    x = calibration_crops(takes, detector, crops, progress=progress)
    model = detector.model
    source = model.session.path
    inputs = model.preprocess(x)
    name = model.session.input_name

    class Crops(ortq.CalibrationDataReader):
        def __init__(self) -> None:
            self.batches = iter(np.array_split(inputs, -(-len(inputs) // CALIBRATION_BATCH)))

        def get_next(self) -> dict | None:
            batch = next(self.batches, None)
            return None if batch is None else {name: batch}

    target = model_path("mediapipe-hand", "hand_landmark_int8")
    staged = target.with_name(f".{target.stem}.{os.getpid()}.onnx")
    floating = staged.with_suffix(".float.onnx")
    try:
        progress("quantize", 0, 1)
        graph = onnx.load(str(source))
        if max(o.version for o in graph.opset_import if o.domain in ("", "ai.onnx")) < QDQ_OPSET:
            graph = version_converter.convert_version(graph, QDQ_OPSET)
        onnx.save(graph, str(floating))
        ortq.quantize_static(str(floating), str(staged), Crops(), quant_format=ortq.QuantFormat.QDQ,
                             activation_type=ortq.QuantType.QUInt8, weight_type=ortq.QuantType.QInt8,
                             per_channel=True, calibrate_method=ortq.CalibrationMethod.MinMax,
                             nodes_to_exclude=kept_in_float(graph))
        progress("quantize", 1, 1)
        record = {"source": source.name, "calibration": [str(t.path.resolve()) for t in takes],
                  "crops": len(x), "method": "onnxruntime static QDQ, int8 per-channel weights, "
                  "uint8 activations, min-max ranges",
                  **_agreement(detector, staged, x, device)}
        staged.replace(target)
    finally:
        staged.unlink(missing_ok=True)
        floating.unlink(missing_ok=True)
    write_atomic(target.with_name(RECORD), (json.dumps(record, indent=1) + "\n").encode())
    return record


def kept_in_float(graph: onnx.ModelProto) -> list[str]:
    """The nodes left in float: the first FLOAT_CONVS convolutions, and the heads (from each output
    of the network back to its first Gemm, MatMul or Conv), which are small."""
    made_by = {out: node for node in graph.graph.node for out in node.output}
    names = [node.name for node in graph.graph.node if node.op_type == "Conv"][:FLOAT_CONVS]
    for output in graph.graph.output:
        node = made_by.get(output.name)
        while node is not None:
            names.append(node.name)
            if node.op_type in ("Gemm", "MatMul", "Conv"):
                break
            node = made_by.get(node.input[0])
    return names


def _agreement(detector: Detector, quantized: Path, x: np.ndarray, device: str) -> dict:
    """How far the int8 model's keypoints are from the float model's on the calibration crops (in
    crop pixels of 224), and its hand presence against theirs."""
    int8 = MediaPipeHand("int8", path=quantized, device=device)
    a, b = detector.model(x), int8(x)
    distance = np.linalg.norm(a[..., :2] - b[..., :2], axis=-1)
    return {"median_px": round(float(np.median(distance)), 3),
            "p90_px": round(float(np.percentile(distance, 90)), 3),
            "presence_max_change": round(float(np.abs(a[:, 0, 2] - b[:, 0, 2]).max()), 4)}
