"""Convert TFLite models to ONNX and record TFLite reference outputs on a fixed input.

Runs inside the private tool environment that `manus-capture models install` creates (tflite2onnx
0.4.1 and the LiteRT interpreter live there, never in the project's environment), so it imports
nothing from this project:

    python _tflite_convert.py OUT_DIR MODEL.tflite [MODEL.tflite ...]

For each MODEL it writes OUT_DIR/MODEL.onnx and OUT_DIR/MODEL.reference.npz (`input`, NHWC as
TFLite takes it, and `output_0..` in the TFLite output order), and prints one JSON line.
"""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

import numpy as np


def _patch_low_rank_layouts() -> None:
    """Let tflite2onnx transpose tensors of rank < 4 that receive an NHWC->NCHW layout.

    The palm detector's PReLU slopes are (1, 1, C) constants broadcast against NHWC feature maps;
    tflite2onnx 0.4.1 propagates the 4-D layout to them and fails with an IndexError. Numpy-style
    broadcasting aligns trailing axes, so (1, 1, C) is (1, 1, 1, C) in NHWC, which becomes
    (1, C, 1, 1) in NCHW: left-pad the shape with ones before the transpose.
    """
    import tflite2onnx.tensor as tensor_module  # only the tool environment has it (see convert)

    original = tensor_module.Tensor.transform

    def transform(self):  # noqa: ANN001, ANN202 - signature of the patched method
        rank = len(self.layout.source)
        if 0 < len(self.shape) < rank:
            self.shape = [1] * (rank - len(self.shape)) + list(self.shape)
        return original(self)

    tensor_module.Tensor.transform = transform


def fixed_input(shape: tuple[int, ...]) -> np.ndarray:
    """The check input: a seeded uniform image in [0, 1], the range the MediaPipe models take."""
    return np.random.default_rng(20250131).random(shape, dtype=np.float32)


def convert(tflite_path: Path, out_dir: Path) -> dict:
    # Only the tool environment has these: imported where used, so the module imports anywhere.
    import tflite2onnx
    from ai_edge_litert.interpreter import Interpreter

    onnx_path = out_dir / (tflite_path.stem + ".onnx")
    tflite2onnx.convert(str(tflite_path), str(onnx_path))

    interpreter = Interpreter(model_path=str(tflite_path))
    interpreter.allocate_tensors()
    (inp,) = interpreter.get_input_details()
    x = fixed_input(tuple(int(d) for d in inp["shape"]))
    interpreter.set_tensor(inp["index"], x)
    interpreter.invoke()
    outputs = {f"output_{i}": interpreter.get_tensor(o["index"])
               for i, o in enumerate(interpreter.get_output_details())}
    np.savez(out_dir / (tflite_path.stem + ".reference.npz"), input=x, **outputs)
    return {"model": tflite_path.stem, "onnx": onnx_path.name, "input_shape": list(x.shape),
            "outputs": {k: list(v.shape) for k, v in outputs.items()}}


def main(argv: list[str]) -> int:
    # tflite2onnx warns once per float16 weight ("may contain error"); the reference check below
    # is what says whether the converted model is right.
    logging.getLogger("tflite2onnx").setLevel(logging.ERROR)
    _patch_low_rank_layouts()
    out_dir = Path(argv[0])
    for path in argv[1:]:
        print(json.dumps(convert(Path(path), out_dir)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
