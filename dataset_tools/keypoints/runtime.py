"""onnxruntime sessions: provider choice, thread count, and errors that name the model file and
the shapes."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import onnxruntime as ort

from manus_core.errors import ModelError


def providers(prefer: str = "auto") -> list[str]:
    """CUDA first when onnxruntime offers it (and `prefer` allows), the CPU provider always last."""
    available = ort.get_available_providers()
    if prefer not in ("auto", "cpu", "cuda"):
        raise ValueError(f"device must be auto, cpu or cuda, got {prefer!r}")
    if prefer == "cuda" and "CUDAExecutionProvider" not in available:
        raise ModelError("device 'cuda' asked but onnxruntime has no CUDAExecutionProvider "
                         "(install onnxruntime-gpu)")
    chosen = ["CUDAExecutionProvider"] if prefer != "cpu" and "CUDAExecutionProvider" in available else []
    return chosen + ["CPUExecutionProvider"]


def default_threads() -> int:
    """The CPU threads of a session not told otherwise: OMP_NUM_THREADS where it is set (a Dask
    worker's nanny sets 1), else the CPUs this process may run on (taskset, a cgroup's cpuset).

    Left to itself onnxruntime starts one thread per core of the machine and pins each to its
    core, outside the process's CPU set: `detect` run on one core (taskset -c 0) ran its network
    on the other core too (20 s of CPU in 10.5 s), and every worker on a shared machine pins its
    threads to the same cores. A count set here is not pinned; one thread gives the same
    keypoints as two, bit for bit (measured on a 2 s take at 1280x720)."""
    try:
        count = int(os.environ.get("OMP_NUM_THREADS", ""))
    except ValueError:
        count = 0
    return count if count > 0 else len(os.sched_getaffinity(0))


class Session:
    """One ONNX model on onnxruntime with a single image input."""

    def __init__(self, path: str | Path, device: str = "auto", threads: int | None = None) -> None:
        self.path = Path(path)
        self.device = device
        if not self.path.is_file():
            raise ModelError(f"{self.path}: no such model file")
        options = ort.SessionOptions()
        options.log_severity_level = 3  # converter leftovers are warnings, not news for the user
        options.intra_op_num_threads = threads or default_threads()
        try:
            self._session = ort.InferenceSession(str(self.path), sess_options=options,
                                                 providers=providers(device))
        except Exception as exc:  # onnxruntime raises its own untyped errors for unreadable files
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise ModelError(f"{self.path}: not a loadable ONNX model ({first})") from None
        inputs = self._session.get_inputs()
        if len(inputs) != 1:
            raise ModelError(f"{self.path}: expected one image input, the model has {len(inputs)}")
        self.input_name = inputs[0].name
        self.input_shape = tuple(d if isinstance(d, int) else None for d in inputs[0].shape)
        self.output_names = [o.name for o in self._session.get_outputs()]
        self.output_shapes = [tuple(o.shape) for o in self._session.get_outputs()]
        self.providers = self._session.get_providers()

    def expect_input(self, shape: tuple[int | None, ...]) -> None:
        """Fail early, naming the file and both shapes, when the model's input does not fit."""
        ok = len(shape) == len(self.input_shape) and all(
            a is None or b is None or a == b for a, b in zip(shape, self.input_shape))
        if not ok:
            raise ModelError(f"{self.path}: the model's input is {_fmt(self.input_shape)}, "
                             f"its specification gives {_fmt(shape)}")

    def run(self, x: np.ndarray) -> list[np.ndarray]:
        try:
            return self._session.run(None, {self.input_name: x})
        except Exception as exc:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise ModelError(f"{self.path}: running on input {_fmt(x.shape)} failed (model input "
                             f"{_fmt(self.input_shape)}): {first}") from None


def _fmt(shape: tuple) -> str:
    return "(" + ", ".join("N" if d is None else str(d) for d in shape) + ")"
