"""Real spherical harmonics up to degree 3, for view-dependent colour.

The basis and its signs follow the convention of the 3D Gaussian splatting papers and of gsplat
(so that coefficients trained elsewhere evaluate to the same colour here), and the colour is
sum_k c_k Y_k(d) + 0.5, clamped at zero.
"""

from __future__ import annotations

import math

import torch

MAX_SH_DEGREE = 3

_PI = math.pi
_C0 = 1 / (2 * math.sqrt(_PI))
_C1 = math.sqrt(3 / (4 * _PI))
_C2 = (math.sqrt(15 / (4 * _PI)), math.sqrt(5 / (16 * _PI)), math.sqrt(15 / (16 * _PI)))
_C3 = (math.sqrt(35 / (32 * _PI)), math.sqrt(105 / (4 * _PI)), math.sqrt(21 / (32 * _PI)),
       math.sqrt(7 / (16 * _PI)), math.sqrt(105 / (16 * _PI)))


def num_sh_bases(degree: int) -> int:
    """Coefficients per colour channel for a degree: (degree + 1)^2."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree must be in 0..{MAX_SH_DEGREE}, got {degree}")
    return (degree + 1) ** 2


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """The real SH basis (..., (degree+1)^2) at directions (...,3) (normalized here)."""
    d = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, _C0)]
    if degree >= 1:
        out += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [_C2[0] * x * y, -_C2[0] * y * z, _C2[1] * (2 * zz - xx - yy), -_C2[0] * x * z,
                _C2[2] * (xx - yy)]
    if degree >= 3:
        out += [-_C3[0] * y * (3 * xx - yy), _C3[1] * x * y * z, -_C3[2] * y * (4 * zz - xx - yy),
                _C3[3] * z * (2 * zz - 3 * xx - 3 * yy), -_C3[2] * x * (4 * zz - xx - yy),
                _C3[4] * z * (xx - yy), -_C3[0] * x * (xx - 3 * yy)]
    return torch.stack(out, dim=-1)


def eval_sh(degree: int, coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Colours (...,3) of SH coefficients (..., K, 3) seen along directions (...,3).

    Only the first (degree+1)^2 coefficients are used, so a model can raise its degree during
    training without changing shape.
    """
    k = num_sh_bases(degree)
    if coeffs.shape[-2] < k:
        raise ValueError(f"degree {degree} needs {k} SH coefficients, got {coeffs.shape[-2]}")
    basis = sh_basis(degree, dirs)
    color = (basis[..., None] * coeffs[..., :k, :]).sum(dim=-2)
    return (color + 0.5).clamp_min(0.0)
