"""Losses and metrics of the splat trainer (SSIM, PSNR, isotropy, LPIPS) and the SH basis."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from manus_capture.splat.gaussians import rgb_to_sh0
from manus_capture.splat.losses import LPIPS, isotropy, load_lpips, psnr, ssim
from manus_capture.splat.sh import eval_sh, num_sh_bases, sh_basis
from manus_core.errors import LPIPSWeightsError

C1, C2 = 0.01 ** 2, 0.03 ** 2


def test_ssim_identical_is_one():
    x = torch.rand(2, 3, 32, 40, generator=torch.Generator().manual_seed(0))
    assert abs(float(ssim(x, x)) - 1.0) < 1e-6


def test_ssim_of_constant_images_is_the_luminance_term():
    a, b = 0.3, 0.7
    x, y = (torch.full((1, 3, 20, 20), v, dtype=torch.float64) for v in (a, b))
    expected = (2 * a * b + C1) / (a * a + b * b + C1)  # contrast-structure term is (C2)/(C2) = 1
    assert math.isclose(float(ssim(x, y)), expected, rel_tol=1e-5)


def test_ssim_of_one_window_matches_the_definition():
    """On an 11x11 image the SSIM map is a single window: compute it by hand in float64."""
    g = np.random.default_rng(1)
    x = g.random((11, 11))
    y = np.clip(x + 0.2 * g.standard_normal((11, 11)), 0, 1)
    r = np.arange(11) - 5.0
    w1 = np.exp(-r * r / (2 * 1.5 ** 2))
    w = np.outer(w1, w1) / np.outer(w1, w1).sum()
    mx, my = (w * x).sum(), (w * y).sum()
    vx, vy = (w * x * x).sum() - mx ** 2, (w * y * y).sum() - my ** 2
    cxy = (w * x * y).sum() - mx * my
    expected = (2 * mx * my + C1) * (2 * cxy + C2) / ((mx ** 2 + my ** 2 + C1) * (vx + vy + C2))
    got = ssim(torch.tensor(x)[None, None], torch.tensor(y)[None, None])
    assert abs(float(got) - expected) < 1e-10
    assert expected < 0.9  # the noise is visible to SSIM


def test_ssim_map_is_the_2d_windows_everywhere():
    """The separable filtering gives the SSIM map of the 11x11 window at every position (float64)."""
    gen = torch.Generator().manual_seed(2)
    x = torch.rand(2, 3, 30, 37, generator=gen, dtype=torch.float64)
    y = (x + 0.1 * torch.randn(x.shape, generator=gen, dtype=torch.float64)).clamp(0, 1)
    r = torch.arange(11, dtype=torch.float64) - 5
    w1 = torch.exp(-r * r / (2 * 1.5 ** 2))
    w = (torch.outer(w1, w1) / torch.outer(w1, w1).sum()).expand(3, 1, 11, 11)

    def f(a):
        return torch.nn.functional.conv2d(a, w, groups=3)

    mx, my = f(x), f(y)
    vx, vy, cxy = f(x * x) - mx ** 2, f(y * y) - my ** 2, f(x * y) - mx * my
    expected = (2 * mx * my + C1) * (2 * cxy + C2) / ((mx ** 2 + my ** 2 + C1) * (vx + vy + C2))
    got = ssim(x, y, reduce=False)
    assert got.shape == (2, 3, 20, 27)
    assert float((got - expected).abs().max()) < 1e-12


def test_psnr_known_value():
    x = torch.zeros(1, 3, 8, 8)
    assert math.isclose(float(psnr(x + 0.1, x)), 20.0, rel_tol=1e-5)  # MSE 0.01


def test_isotropy_zero_at_the_target_ratio():
    s = torch.tensor([[0.4, 1.0, 0.7], [2.0, 0.8, 1.5]])  # min/max = 0.4 for both
    assert float(isotropy(s)) < 1e-12
    assert math.isclose(float(isotropy(torch.ones(3, 3))), 0.36, rel_tol=1e-6)
    assert math.isclose(float(isotropy(torch.tensor([[0.1, 1.0, 1.0]]))), 0.09, rel_tol=1e-6)


def test_lpips_off_with_a_warning_without_weights(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))   # a cache where nothing is installed
    with pytest.warns(UserWarning, match="models install lpips-alex"):
        assert load_lpips(None) is None


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_loads_a_user_state_dict(tmp_path, net):
    from safetensors.torch import save_file

    torch.manual_seed(0)
    state = {k: v.clone() for k, v in LPIPS(net).state_dict().items()}
    # The linear heads of real LPIPS weights are non-negative.
    for k in state:
        if k.startswith("lin"):
            state[k] = state[k].abs()
    path = tmp_path / f"lpips_{net}.safetensors"
    save_file(state, str(path))
    model = load_lpips(path, net)
    x = torch.rand(1, 3, 64, 64)
    assert float(model(x, x)) == 0.0
    assert float(model(x, torch.rand(1, 3, 64, 64))) > 0
    assert not any(p.requires_grad for p in model.parameters())
    torch.save(state, tmp_path / "as_torch.pth")
    assert load_lpips(tmp_path / "as_torch.pth", net) is not None


def test_lpips_rejects_foreign_weights(tmp_path):
    torch.save({"features.0.weight": torch.zeros(1)}, tmp_path / "other.pth")
    with pytest.raises(LPIPSWeightsError, match="other.pth"):
        load_lpips(tmp_path / "other.pth", "alex")


def test_sh_basis_is_orthonormal():
    # Fibonacci sphere: a near-uniform quadrature of the sphere.
    n = 20000
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5 ** 0.5) * i
    dirs = torch.stack([torch.sqrt(1 - z * z) * torch.cos(phi), torch.sqrt(1 - z * z) * torch.sin(phi), z], -1)
    Y = sh_basis(3, dirs)
    gram = 4 * math.pi * Y.T @ Y / n
    assert torch.allclose(gram, torch.eye(num_sh_bases(3), dtype=torch.float64), atol=2e-3)


def test_sh_degree_zero_gives_the_colour_back():
    rgb = torch.tensor([[0.1, 0.5, 0.9]])
    coeffs = torch.zeros(1, 16, 3)
    coeffs[:, 0] = rgb_to_sh0(rgb)
    coeffs[:, 1:] = 0.3  # ignored at degree 0
    assert torch.allclose(eval_sh(0, coeffs, torch.tensor([[0.3, -0.2, 0.9]])), rgb, atol=1e-6)
