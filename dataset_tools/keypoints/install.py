"""Model installation: fetch MediaPipe's hand models, convert them to ONNX, check, cache.

`install("mediapipe-hand")` downloads the `mediapipe==0.10.21` wheel with `pip download --no-deps`
(the wheel carries the Apache-2.0 .tflite models; nothing of MediaPipe is installed), extracts the
hand landmark (full, lite) and palm detection (full, lite) models, converts them with tflite2onnx
in a private tool environment under the cache directory (tflite2onnx and the LiteRT interpreter
never enter the project's environment), checks every converted model against the TFLite
interpreter on a fixed input, and moves the result into place in one rename.

Layout of the cache (`$XDG_CACHE_HOME` or `~/.cache`, then `manus-capture/`):

    models/mediapipe-hand/manifest.json        what was installed, hashes, check results
    models/mediapipe-hand/hand_landmark_full.onnx, hand_landmark_lite.onnx,
                          palm_detection_full.onnx, palm_detection_lite.onnx
    models/mediapipe-hand/tflite/*.tflite      the originals from the wheel
    models/mediapipe-hand/hand_landmark_int8.onnx, int8.json
                                               after `models quantize` (quantize.py); gone with --force
    tools/tflite2onnx-0.4.1/                   the private converter environment (and TFLite runtime)

`pip_download`, `install_work` and `publish` serve LPIPS's install as well
(manus_capture/splat/lpips_install.py).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import venv
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
from onnx import numpy_helper

from manus_core.errors import InstallError, ModelError, ModelNotInstalledError
from manus_core.progress import Progress, silent
from manus_core.provenance import file_sha256

INSTALL_HINT = "manus-capture models install {name}"

# The converter environment is pinned: tflite2onnx is unmaintained since 2021, so only a set that
# was seen to convert these models is trusted. The install check catches any drift regardless.
TOOL_NAME = "tflite2onnx-0.4.1"
TOOL_REQUIREMENTS = ("tflite2onnx==0.4.1", "tflite==2.18.0", "onnx==1.23.2", "ai-edge-litert==2.3.0",
                     "numpy>=1.26,<3", "flatbuffers>=24")

# Converted outputs must match TFLite within this (landmarks are in input pixels, up to ~224, so
# this is a thousandth of a pixel per pixel; float16 weights dequantized the same way on both sides
# agree to ~1e-4 px in practice).
CHECK_RTOL = 1e-3
CHECK_ATOL = 1e-3


@dataclass(frozen=True)
class Bundle:
    """An installable set of models taken from one pip wheel."""

    name: str
    requirement: str
    members: dict[str, str]   # ONNX file stem -> path of the .tflite inside the wheel
    description: str


BUNDLES: dict[str, Bundle] = {
    "mediapipe-hand": Bundle(
        name="mediapipe-hand",
        requirement="mediapipe==0.10.21",
        members={
            "hand_landmark_full": "mediapipe/modules/hand_landmark/hand_landmark_full.tflite",
            "hand_landmark_lite": "mediapipe/modules/hand_landmark/hand_landmark_lite.tflite",
            "palm_detection_full": "mediapipe/modules/palm_detection/palm_detection_full.tflite",
            "palm_detection_lite": "mediapipe/modules/palm_detection/palm_detection_lite.tflite",
        },
        description="MediaPipe hand landmarks (21 joints, full and lite) and palm detector, Apache-2.0",
    ),
}


def cache_dir() -> Path:
    """$XDG_CACHE_HOME/manus-capture, or ~/.cache/manus-capture (read at call time, for tests)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "manus-capture"


def bundle_dir(name: str) -> Path:
    return cache_dir() / "models" / name


def _bundle(name: str) -> Bundle:
    try:
        return BUNDLES[name]
    except KeyError:
        raise ModelError(f"unknown model {name!r}: installable models are {', '.join(BUNDLES)}") from None


def installed_manifest(name: str) -> dict | None:
    """The manifest of an installed bundle, or None when it is not (completely) installed."""
    directory = bundle_dir(name)
    try:
        manifest = json.loads((directory / "manifest.json").read_text())
    except (FileNotFoundError, json.JSONDecodeError, UnicodeDecodeError):
        return None
    # a manifest that is not ours (edited, another tool's) counts as not installed: install again
    if not isinstance(manifest, dict) or not isinstance(manifest.get("files", {}), dict):
        return None
    if not all((directory / f).is_file() for f in manifest.get("files", {})):
        return None
    return manifest


def model_path(name: str, stem: str) -> Path:
    """Path of one installed ONNX file; raises ModelNotInstalledError naming the install command."""
    if installed_manifest(name) is None:
        raise ModelNotInstalledError(
            f"model {name!r} is not installed in {bundle_dir(name)}: run `{INSTALL_HINT.format(name=name)}`")
    return bundle_dir(name) / f"{stem}.onnx"


def run_tool(cmd: list[str], what: str, hint: str = "") -> str:
    """Run a command; its output, or InstallError naming `what` with the last line it printed."""
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        lines = [ln.strip() for ln in (proc.stderr or proc.stdout).splitlines() if ln.strip()]
        last = lines[-1] if lines else f"exit code {proc.returncode}"
        raise InstallError(f"{what} failed{hint}: {last}")
    return proc.stdout


def pip_download(requirement: str, dest: Path, source: bool = False) -> Path:
    """Download one package file with `pip download --no-deps` into dest (created), nothing
    installed: the wheel for this interpreter and platform, or with `source` the source
    distribution (its metadata prepared with this environment's setuptools). Returns its path."""
    kind = ["--no-binary=:all:", "--no-build-isolation"] if source else ["--only-binary=:all:"]
    run_tool([sys.executable, "-m", "pip", "download", "--no-deps", *kind, "--no-input",
              "--disable-pip-version-check", "--progress-bar", "off", "-d", str(dest), requirement],
             f"`pip download --no-deps {requirement}`", " (is the network or the package index reachable?)")
    files = sorted(f for f in Path(dest).iterdir() if f.name.endswith((".whl", ".tar.gz", ".zip")))
    if not files:
        raise InstallError(f"`pip download {requirement}` left no package file in {dest}")
    return files[0]


def tool_python() -> Path | None:
    """The private environment's interpreter (tflite2onnx, LiteRT), or None before an install made it."""
    env = cache_dir() / "tools" / TOOL_NAME
    python = env / "bin" / "python"
    return python if (env / ".complete").is_file() and python.exists() else None


def _tool_env(progress: Progress) -> Path:
    """The private converter environment; created once, reused by later installs."""
    env = cache_dir() / "tools" / TOOL_NAME
    python = env / "bin" / "python"
    marker = env / ".complete"
    if tool_python() is not None:
        return python
    if env.exists():
        shutil.rmtree(env)  # an environment whose creation was interrupted
    progress("converter environment", 0, 1)
    venv.EnvBuilder(with_pip=True, clear=True).create(env)
    run_tool([str(python), "-m", "pip", "install", "--no-input", "--disable-pip-version-check", "-q",
              *TOOL_REQUIREMENTS], f"installing the converter ({', '.join(TOOL_REQUIREMENTS)}) into {env}",
             " (is the network or the package index reachable?)")
    marker.write_text("\n".join(TOOL_REQUIREMENTS) + "\n")
    progress("converter environment", 1, 1)
    return python


def make_batch_dynamic(model: onnx.ModelProto) -> None:
    """Turn the converter's fixed batch of 1 into a symbolic batch so crops run in one call.

    Inputs and outputs get a symbolic first axis; Reshape targets that start with 1 get 0 (copy the
    input's first axis); Resize nodes that name output `sizes` (which include the batch) get the
    equivalent `scales` instead; stale intermediate shapes are dropped so that shape inference redoes
    them.
    """
    inferred = onnx.shape_inference.infer_shapes(model)
    shapes = {v.name: [d.dim_value for d in v.type.tensor_type.shape.dim]
              for v in list(inferred.graph.value_info) + list(inferred.graph.input)}
    initializers = {t.name: t for t in model.graph.initializer}
    for node in model.graph.node:
        if node.op_type == "Resize" and len(node.input) == 4 and node.input[3] in initializers:
            sizes = numpy_helper.to_array(initializers[node.input[3]]).astype(np.float64)
            scales = (sizes / np.asarray(shapes[node.input[0]], dtype=np.float64)).astype(np.float32)
            scales_name = f"{node.name or node.output[0]}/scales"
            model.graph.initializer.append(numpy_helper.from_array(scales, scales_name))
            node.input[2] = scales_name
            del node.input[3]
    for value in list(model.graph.input) + list(model.graph.output):
        dim = value.type.tensor_type.shape.dim[0]
        dim.ClearField("dim_value")
        dim.dim_param = "N"
    for node in model.graph.node:
        if node.op_type == "Reshape" and node.input[1] in initializers:
            shape = numpy_helper.to_array(initializers[node.input[1]]).copy()
            if shape.size and shape[0] == 1:
                shape[0] = 0
                initializers[node.input[1]].CopyFrom(numpy_helper.from_array(shape.astype(np.int64),
                                                                             node.input[1]))
    used = {name for node in model.graph.node for name in node.input}
    kept = [t for t in model.graph.initializer if t.name in used]
    del model.graph.initializer[:]
    model.graph.initializer.extend(kept)
    del model.graph.value_info[:]


def check_against_reference(onnx_path: Path, reference: Path) -> float:
    """Run the ONNX model on the TFLite check input, as one crop and as a batch of two.

    Returns the largest absolute difference; raises InstallError naming the file when an output
    differs beyond CHECK_RTOL/CHECK_ATOL or has the wrong shape.
    """
    ref = np.load(reference)
    session = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    x = ref["input"].transpose(0, 3, 1, 2)  # tflite2onnx turns the NHWC input into NCHW
    outputs = session.run(None, {session.get_inputs()[0].name: np.concatenate([x, x])})
    worst = 0.0
    for i, out in enumerate(outputs):
        expected = ref[f"output_{i}"]
        if out.shape[1:] != expected.shape[1:] or out.shape[0] != 2:
            raise InstallError(f"{onnx_path}: output {i} has shape {out.shape}, TFLite gives "
                               f"{expected.shape} (batch of 2 asked)")
        for b in range(2):
            if not np.allclose(out[b], expected[0], rtol=CHECK_RTOL, atol=CHECK_ATOL):
                diff = float(np.abs(out[b] - expected[0]).max())
                raise InstallError(f"{onnx_path}: output {i} differs from TFLite by up to {diff:.4g} "
                                   f"on the check input (tolerance {CHECK_ATOL} + {CHECK_RTOL} x |value|)")
        worst = max(worst, float(np.abs(out - expected).max()))
    return worst


@contextmanager
def install_work(name: str) -> Iterator[Path]:
    """A work folder for installing model `name`, beside the cache's models (one file system, for
    publish's rename), removed afterwards."""
    parent = bundle_dir(name).parent
    parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{name}.", dir=parent))
    try:
        yield work
    finally:
        shutil.rmtree(work, ignore_errors=True)


def publish(staged: Path, name: str, manifest: dict) -> None:
    """Write `manifest` into the staged folder and put it in place of model `name` in one rename."""
    (staged / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    final = bundle_dir(name)
    if final.exists():
        shutil.rmtree(final)
    os.replace(staged, final)


def install(name: str, force: bool = False, progress: Progress = silent) -> bool:
    """Install a model bundle into the cache; returns False when it was already installed.

    Reports the stages "download", "converter environment" (the first time), "convert" and
    "check" (one model after the other); the check results go into the manifest."""
    bundle = _bundle(name)
    if not force and installed_manifest(name) is not None:
        return False
    with install_work(name) as work:
        progress("download", 0, 1)
        wheel = pip_download(bundle.requirement, work / "wheel")
        progress("download", 1, 1)
        tflite_dir = work / "tflite"
        tflite_dir.mkdir()
        with zipfile.ZipFile(wheel) as zf:
            for stem, member in bundle.members.items():
                try:
                    (tflite_dir / f"{stem}.tflite").write_bytes(zf.read(member))
                except KeyError:
                    raise InstallError(f"{wheel.name}: has no {member}") from None
        python = _tool_env(progress)
        progress("convert", 0, 1)
        out = work / "out"
        out.mkdir()
        run_tool([str(python), str(Path(__file__).with_name("_tflite_convert.py")), str(out),
                  *(str(tflite_dir / f"{stem}.tflite") for stem in bundle.members)],
                 f"converting the models of {wheel.name} with tflite2onnx")
        progress("convert", 1, 1)
        files, checks = {}, {}
        progress("check", 0, len(bundle.members))
        for stem in bundle.members:
            onnx_path = out / f"{stem}.onnx"
            model = onnx.load(str(onnx_path))
            make_batch_dynamic(model)
            onnx.checker.check_model(model)
            onnx.save(model, str(onnx_path))
            checks[stem] = check_against_reference(onnx_path, out / f"{stem}.reference.npz")
            files[onnx_path.name] = file_sha256(onnx_path)
            progress("check", len(files), len(bundle.members))
        staged = work / "staged"
        staged.mkdir()
        for filename in files:
            os.replace(out / filename, staged / filename)
        # The originals stay beside the conversions: benchmarks compare against the TFLite runtime.
        os.replace(tflite_dir, staged / "tflite")
        manifest = {"name": name, "source": bundle.requirement, "wheel": wheel.name,
                    "wheel_sha256": file_sha256(wheel), "converter": list(TOOL_REQUIREMENTS),
                    "files": files, "check_max_abs_diff": checks,
                    "installed": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        publish(staged, name, manifest)
        return True


def list_models() -> list[dict]:
    """One row per installable bundle: name, description, installed (bool), path, files."""
    rows = []
    for name, bundle in BUNDLES.items():
        manifest = installed_manifest(name)
        rows.append({"name": name, "description": bundle.description, "installed": manifest is not None,
                     "path": str(bundle_dir(name)), "files": sorted(manifest["files"]) if manifest else []})
    return rows
