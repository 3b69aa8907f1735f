"""Hand keypoint speed: per-crop latency and batched throughput, full vs lite, ONNX Runtime vs TFLite.

    .venv/bin/python benchmarks/bench_keypoints.py [--threads N] [--device auto|cpu|cuda]

Needs `manus-capture models install mediapipe-hand`. Side by side, in one run:
  1. the landmark network alone, one crop per call vs a batch of 32, full vs lite, on onnxruntime;
  2. the same .tflite models on the TFLite (LiteRT) interpreter, what MediaPipe itself runs, one crop
     per call (its models take one) - from the converter environment the install created;
  3. the whole Detector on 1280x720 frames with one hand each: tracking (hand angle known: a crop and
     one refinement) vs search (angle unknown: 4 turns and one refinement), and the palm detector.
With a CUDA provider (onnxruntime-gpu on a GPU machine) the same table runs on it too.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dataset_tools.keypoints import hand_keypoint_detector  # noqa: E402
from dataset_tools.keypoints.install import bundle_dir, model_path, tool_python  # noqa: E402
from dataset_tools.keypoints.models import MediaPipeHand  # noqa: E402
from dataset_tools.keypoints.palm import PalmDetector  # noqa: E402

BATCH = 32

TFLITE_TIMER = """
import json, sys, time
import numpy as np
from ai_edge_litert.interpreter import Interpreter
path, threads, reps = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
it = Interpreter(model_path=path, num_threads=threads)
it.allocate_tensors()
inp = it.get_input_details()[0]
x = np.random.default_rng(0).random(inp["shape"], dtype=np.float32)
it.set_tensor(inp["index"], x); it.invoke()
t = []
for _ in range(reps):
    s = time.perf_counter(); it.set_tensor(inp["index"], x); it.invoke(); t.append(time.perf_counter() - s)
print(json.dumps(sorted(t)[len(t) // 2]))
"""


def median_time(fn, reps: int) -> float:
    fn()  # warm-up: allocations, thread pools
    times = []
    for _ in range(reps):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def tflite_latency(stem: str, threads: int, reps: int) -> float | None:
    python = tool_python()
    path = bundle_dir("mediapipe-hand") / "tflite" / f"{stem}.tflite"
    if python is None or not path.is_file():
        return None
    out = subprocess.run([str(python), "-c", TFLITE_TIMER, str(path), str(threads), str(reps)],
                         capture_output=True, text=True)
    return float(json.loads(out.stdout.strip().splitlines()[-1])) if out.returncode == 0 else None


def network_table(device: str, threads: int) -> None:
    rng = np.random.default_rng(0)
    crops = rng.integers(0, 256, (BATCH, 224, 224, 3), dtype=np.uint8)
    print(f"\n1-2. landmark network alone ({device}, {threads} thread(s)); median of repeated calls")
    print(f"{'model':<8} {'runtime':<26} {'ms/crop':>8} {'crops/s':>8}")
    rows = {}
    for variant in ("full", "lite"):
        model = MediaPipeHand(variant, device=device, threads=threads)
        one = median_time(lambda: model(crops[:1]), 30)
        many = median_time(lambda: model(crops), 5) / BATCH
        tfl = tflite_latency(f"hand_landmark_{variant}", threads, 30) if device == "cpu" else None
        rows[variant] = (one, many, tfl)
        print(f"{variant:<8} {'onnxruntime, 1 per call':<26} {one * 1e3:8.2f} {1 / one:8.0f}")
        print(f"{variant:<8} {f'onnxruntime, {BATCH} per call':<26} {many * 1e3:8.2f} {1 / many:8.0f}")
        if tfl is not None:
            print(f"{variant:<8} {'TFLite/LiteRT, 1 per call':<26} {tfl * 1e3:8.2f} {1 / tfl:8.0f}")
    for variant, (one, many, tfl) in rows.items():
        line = f"{variant}: batched/one-at-a-time throughput x{one / many:.2f}"
        if tfl is not None:
            line += f"; onnxruntime vs TFLite per crop x{tfl / one:.2f} (>1: onnxruntime faster)"
        print(line)
    print(f"full vs lite per crop (one at a time): lite x{rows['full'][0] / rows['lite'][0]:.2f} faster, "
          f"batched x{rows['full'][1] / rows['lite'][1]:.2f}")


def detector_table(device: str, threads: int) -> None:
    rng = np.random.default_rng(1)
    frames = [rng.integers(0, 256, (720, 1280, 3), dtype=np.uint8) for _ in range(8)]
    boxes = [np.array([[600.0, 300.0, 760.0, 470.0]]) for _ in frames]
    angles = [np.array([0.3]) for _ in frames]
    print(f"\n3. Detector on {len(frames)} frames of 1280x720, one hand each ({device}, {threads} thread(s))")
    print(f"{'pipeline':<44} {'ms/frame':>9} {'frames/s':>9}")
    results = {}
    for name in ("mediapipe-hand", "mediapipe-hand-lite"):
        det = hand_keypoint_detector(name, device=device, threads=threads)
        tracked = median_time(lambda: det.detect_many(frames, boxes, angles), 3) / len(frames)
        searched = median_time(lambda: det.detect_many(frames, boxes), 3) / len(frames)
        results[name] = (tracked, searched)
        print(f"{name + ', angle known (2 passes)':<44} {tracked * 1e3:9.2f} {1 / tracked:9.1f}")
        print(f"{name + ', angle searched (4 turns + 1 pass)':<44} {searched * 1e3:9.2f} {1 / searched:9.1f}")
    palm = PalmDetector(device=device, threads=threads)
    one = median_time(lambda: palm.detect(frames[:1]), 10)
    many = median_time(lambda: palm.detect(frames), 3) / len(frames)
    print(f"{'palm detector, 1 frame per call':<44} {one * 1e3:9.2f} {1 / one:9.1f}")
    print(f"{f'palm detector, {len(frames)} frames per call':<44} {many * 1e3:9.2f} {1 / many:9.1f}")
    t, s = results["mediapipe-hand"]
    print(f"tracking vs search: x{s / t:.2f} faster when the hand angle is known; "
          f"palm batched vs one-at-a-time x{one / many:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1, help="onnxruntime/TFLite threads (default 1)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    args = parser.parse_args()
    model_path("mediapipe-hand", "hand_landmark_full")  # fails with the install command if missing
    import onnxruntime as ort

    devices = ["cpu"]
    if args.device in ("auto", "cuda") and "CUDAExecutionProvider" in ort.get_available_providers():
        devices.append("cuda")
    if args.device == "cuda":
        devices = ["cuda"]
    print(f"onnxruntime {ort.__version__}, providers {ort.get_available_providers()}")
    for device in devices:
        network_table(device, args.threads)
        detector_table(device, args.threads)


if __name__ == "__main__":
    main()
