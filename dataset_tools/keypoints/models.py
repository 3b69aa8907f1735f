"""Keypoint models: MediaPipe's hand landmark network, and SimCC / heatmap models given by a TOML spec.

A model turns a batch of crops (N,H,W,3) BGR uint8 into keypoints (N,21,3) [x, y, confidence] in
crop pixels, in the MediaPipe joint order. Where crops come from and how keypoints go back to the
image is the Detector's business; a model only says how it wants its crops (`CropSpec`).

Spec file (TOML) for models 2 and 3; paths are relative to the spec file:

    kind = "simcc"                      # simcc | heatmap
    model = "rtmpose-m-hand.onnx"
    input_size = [256, 256]             # width, height
    layout = "NCHW"                     # NCHW | NHWC
    color = "RGB"                       # channel order the network takes: RGB | BGR
    mean = [123.675, 116.28, 103.53]    # per channel in `color` order, on 0..255 values
    std = [58.395, 57.12, 57.375]
    box_scale = 1.25                    # crop = hand box enlarged by this, to the input's aspect
    keypoints = [0, 1, ..., 20]         # for each MediaPipe joint, the model's joint index (-1: none)

    [simcc]                             # kind = "simcc"
    split_ratio = 2.0                   # bins per input pixel
    outputs = ["simcc_x", "simcc_y"]    # optional; default: the first two outputs
    softmax = false                     # apply a softmax first (logits in, probabilities as confidence)

    [heatmap]                           # kind = "heatmap"
    output = "heatmaps"                 # optional; default: the first output
    refine = "quarter"                  # none | quarter | parabola
    sigmoid = false
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import Field

from manus_core.errors import ModelError, ModelNotInstalledError
from manus_core.validation import CLOSED, Bool, Float, Int, Str, between, validate, worded

from . import decoding
from .install import model_path
from .runtime import Session

NUM_JOINTS = 21
JOINT_NAMES = ("wrist",
               "thumb1", "thumb2", "thumb3", "thumb4",
               "index1", "index2", "index3", "index4",
               "middle1", "middle2", "middle3", "middle4",
               "ring1", "ring2", "ring3", "ring4",
               "pinky1", "pinky2", "pinky3", "pinky4")


@dataclass(frozen=True)
class CropSpec:
    """How a model wants its crops.

    width, height: network input. box_scale: the crop rect is the hand box's extent times this.
    rotate: crops are turned to the hand axis (needs a keypoint estimate, so only on refinement).
    refine: re-crops from the model's own keypoints after the first pass (MediaPipe's tracking).
    """

    width: int
    height: int
    box_scale: float
    rotate: bool = False
    refine: int = 0


class KeypointModel:
    """Base: an ONNX session plus pre-processing and decoding."""

    name: str
    crop: CropSpec
    session: Session

    def preprocess(self, crops: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def decode(self, outputs: list[np.ndarray]) -> np.ndarray:
        raise NotImplementedError

    def __call__(self, crops: np.ndarray) -> np.ndarray:
        """(N,H,W,3) BGR uint8 crops -> (N,21,3) [x, y, confidence] in crop pixels."""
        return self.decode(self.session.run(self.preprocess(crops)))


class MediaPipeHand(KeypointModel):
    """MediaPipe hand landmark (full or lite), converted to ONNX by `models install mediapipe-hand`, or
    the full one in int8 (`models quantize`, quantize.py).

    Input: 224x224 RGB in [0, 1], the hand upright. Outputs: 21 (x, y, z) landmarks in input pixels
    (continuous coordinates spanning the input edge to edge), a hand-presence probability, the
    handedness and world landmarks. The network has no per-joint confidence: every joint of a hand
    gets its presence probability.
    """

    SIZE = 224
    # MediaPipe crops a tracked hand at 2.0x the extent of its knuckles (boxes.rects_from_keypoints);
    # on real hands that square is 1.3x to 2.2x, median 1.7x, the longer side of the box around all
    # 21 joints, so a joint box enlarged 1.7x frames the hand as the network was trained to see it.
    BOX_SCALE = 1.7

    def __init__(self, variant: str = "full", path: str | Path | None = None, device: str = "auto",
                 threads: int | None = None, refine: int = 1) -> None:
        if variant not in ("full", "lite", "int8"):
            raise ModelError(f"MediaPipe hand variant must be full, lite or int8, got {variant!r}")
        path = Path(path) if path is not None else model_path("mediapipe-hand", f"hand_landmark_{variant}")
        if variant == "int8" and not path.is_file():
            raise ModelNotInstalledError(
                f"{path}: no int8 hand landmark model yet: run `manus-capture models quantize mediapipe-hand "
                "--calibration TAKE` on one or more of your takes")
        self.name = "mediapipe-hand" + ("" if variant == "full" else f"-{variant}")
        self.session = Session(path, device=device, threads=threads)
        self.session.expect_input((None, 3, self.SIZE, self.SIZE))
        if len(self.session.output_names) != 4:
            raise ModelError(f"{path}: expected the 4 outputs of MediaPipe's hand landmark model, "
                             f"got shapes {self.session.output_shapes}")
        self.crop = CropSpec(self.SIZE, self.SIZE, self.BOX_SCALE, rotate=True, refine=refine)

    def preprocess(self, crops: np.ndarray) -> np.ndarray:
        rgb = crops[..., ::-1].transpose(0, 3, 1, 2)
        return np.ascontiguousarray(rgb, dtype=np.float32) * np.float32(1 / 255)

    def decode(self, outputs: list[np.ndarray]) -> np.ndarray:
        landmarks, presence = outputs[0], outputs[1]
        xy = landmarks.reshape(len(landmarks), NUM_JOINTS, 3)[..., :2].astype(np.float64) - 0.5
        conf = np.broadcast_to(presence.reshape(-1, 1, 1).astype(np.float64), xy.shape[:2] + (1,))
        return np.concatenate([xy, conf], axis=-1)


@dataclass(frozen=True)
class ModelSpec:
    """A SimCC or heatmap model as described by its TOML file (see the module docstring)."""

    source: Path
    kind: str
    model: Path
    input_size: tuple[int, int]
    layout: str
    color: str
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    box_scale: float
    keypoints: tuple[int, ...]
    split_ratio: float = 2.0
    outputs: tuple[str, ...] = ()
    softmax: bool = False
    refine: str = "quarter"
    sigmoid: bool = False


Positive = Annotated[Float, Field(gt=0)]
InputSide = Annotated[Int, Field(ge=16, le=4096)]   # pixels: no hand keypoint network takes less or more


@dataclass(frozen=True)
class _SimccTable:
    __pydantic_config__ = CLOSED   # unknown keys are errors

    split_ratio: between(Float, 0, 16, "bins per input pixel", low_open=True) = 2.0
    outputs: tuple[Str, ...] = ()
    softmax: Bool = False


@dataclass(frozen=True)
class _HeatmapTable:
    __pydantic_config__ = CLOSED   # unknown keys are errors

    output: Str = ""
    refine: Literal[decoding.REFINES] = "quarter"
    sigmoid: Bool = False


@dataclass(frozen=True)
class _SpecFile:
    """A spec file as written; load_spec makes it a ModelSpec."""

    __pydantic_config__ = CLOSED   # unknown keys are errors: a misspelt key would be ignored

    kind: Literal["simcc", "heatmap"]
    model: Annotated[Str, Field(min_length=1)]
    input_size: Annotated[tuple[InputSide, InputSide],
                          worded("expected [width, height] in pixels, each in 16..4096, got {value}")]
    layout: Literal["NCHW", "NHWC"] = "NCHW"
    color: Literal["RGB", "BGR"] = "RGB"
    mean: tuple[Float, Float, Float] = (0.0, 0.0, 0.0)
    std: tuple[Positive, Positive, Positive] = (1.0, 1.0, 1.0)
    box_scale: between(Float, 1, 4) = 1.25   # the crop is the hand box enlarged by this
    keypoints: Annotated[tuple[Annotated[Int, Field(ge=-1)], ...], Field(min_length=NUM_JOINTS, max_length=NUM_JOINTS),
                         worded(f"expected {NUM_JOINTS} model joint indices (-1 for none) in the MediaPipe order, "
                                "got {value}")] = tuple(range(NUM_JOINTS))
    simcc: _SimccTable = _SimccTable()
    heatmap: _HeatmapTable = _HeatmapTable()


def load_spec(path: str | Path) -> ModelSpec:
    """Read and validate a model spec; errors name the file and the key."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ModelError(f"{path}: no such model spec") from None
    except tomllib.TOMLDecodeError as exc:
        raise ModelError(f"{path}: not valid TOML ({exc})") from None
    spec = validate(_SpecFile, doc, str(path), ModelError)
    given = [k for k in spec.keypoints if k >= 0]
    if not given:
        raise ModelError(f"{path}: keypoints: no joint is given (all -1)")
    twice = next((k for k in given if given.count(k) > 1), None)
    if twice is not None:
        joints = [JOINT_NAMES[j] for j, k in enumerate(spec.keypoints) if k == twice]
        raise ModelError(f"{path}: keypoints: model joint {twice} is given for {' and '.join(joints)}; "
                         "each model joint is one MediaPipe joint")
    if spec.kind == "simcc":
        extra = dict(split_ratio=spec.simcc.split_ratio, outputs=spec.simcc.outputs, softmax=spec.simcc.softmax)
    else:
        extra = dict(outputs=(spec.heatmap.output,) if spec.heatmap.output else (), refine=spec.heatmap.refine,
                     sigmoid=spec.heatmap.sigmoid)
    return ModelSpec(source=path, kind=spec.kind, model=(path.parent / spec.model).resolve(),
                     input_size=spec.input_size, layout=spec.layout, color=spec.color, mean=spec.mean,
                     std=spec.std, box_scale=spec.box_scale, keypoints=spec.keypoints, **extra)


class SpecModel(KeypointModel):
    """A top-down SimCC or heatmap model from a spec; crops are axis-aligned (no rotation)."""

    def __init__(self, spec: ModelSpec | str | Path, device: str = "auto",
                 threads: int | None = None) -> None:
        self.spec = spec if isinstance(spec, ModelSpec) else load_spec(spec)
        self.name = self.spec.source.stem
        self.session = Session(self.spec.model, device=device, threads=threads)
        w, h = self.spec.input_size
        self.session.expect_input((None, 3, h, w) if self.spec.layout == "NCHW" else (None, h, w, 3))
        self._outputs = self._output_indices()
        self.crop = CropSpec(w, h, self.spec.box_scale)
        order = self.spec.color == "RGB"
        self._mean = np.array(self.spec.mean[::-1] if order else self.spec.mean, np.float32)
        self._scale = 1 / np.array(self.spec.std[::-1] if order else self.spec.std, np.float32)

    def _output_indices(self) -> list[int]:
        names = self.session.output_names
        want = self.spec.outputs or tuple(names[: 2 if self.spec.kind == "simcc" else 1])
        needed = 2 if self.spec.kind == "simcc" else 1
        missing = [n for n in want if n not in names]
        if len(want) != needed or missing:
            raise ModelError(f"{self.spec.source}: needs {needed} output(s) of {self.session.path}, "
                             f"which has {names}; asked for {list(want)}")
        return [names.index(n) for n in want]

    def preprocess(self, crops: np.ndarray) -> np.ndarray:
        # Normalize in BGR with reversed constants, then flip channels once: one pass over the pixels.
        x = (crops.astype(np.float32) - self._mean) * self._scale
        if self.spec.color == "RGB":
            x = x[..., ::-1]
        if self.spec.layout == "NCHW":
            x = x.transpose(0, 3, 1, 2)
        return np.ascontiguousarray(x)

    def decode(self, outputs: list[np.ndarray]) -> np.ndarray:
        spec = self.spec
        if spec.kind == "simcc":
            sx, sy = (outputs[i] for i in self._outputs)
            raw = decoding.decode_simcc(sx, sy, spec.split_ratio, spec.softmax)
        else:
            raw = decoding.decode_heatmaps(outputs[self._outputs[0]], spec.input_size, spec.refine,
                                           spec.sigmoid)
        return reorder(raw, spec.keypoints, self.spec.source)


def reorder(raw: np.ndarray, keypoints: tuple[int, ...], source: Path | str) -> np.ndarray:
    """Pick the model's joints into the MediaPipe order; absent joints are NaN with confidence 0."""
    index = np.asarray(keypoints)
    if index.max() >= raw.shape[1]:
        raise ModelError(f"{source}: keypoints refers to joint {index.max()}, the model gives "
                         f"{raw.shape[1]} joints")
    out = raw[:, np.maximum(index, 0)]
    out[:, index < 0] = (np.nan, np.nan, 0.0)
    return out


def load_model(name: str | Path = "mediapipe-hand", device: str = "auto",
               threads: int | None = None) -> KeypointModel:
    """`mediapipe-hand`, `mediapipe-hand-lite`, `mediapipe-hand-int8` (after `models quantize`), or a
    path to a model spec (.toml)."""
    text = str(name)
    if text in ("mediapipe-hand", "mediapipe-hand-full"):
        return MediaPipeHand("full", device=device, threads=threads)
    if text in ("mediapipe-hand-lite", "mediapipe-hand-int8"):
        return MediaPipeHand(text.rsplit("-", 1)[1], device=device, threads=threads)
    if text.endswith(".toml"):
        return SpecModel(text, device=device, threads=threads)
    if text.endswith(".onnx"):
        raise ModelError(f"{text}: an ONNX file needs a spec (.toml) that says how to decode it; "
                         "see docs/keypoints.md")
    raise ModelError(f"unknown keypoint model {text!r}: use mediapipe-hand, mediapipe-hand-lite, "
                     "mediapipe-hand-int8 or a model spec (.toml)")
