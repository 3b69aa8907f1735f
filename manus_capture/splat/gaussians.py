"""3D Gaussians: the trainable parameters and the geometry derived from them.

A Gaussian has a mean, a rotation (unit quaternion, w x y z), a scale per axis (stored as its
logarithm so that the optimizer cannot make it negative), an opacity (stored as a logit) and a
colour as spherical-harmonics coefficients of a configurable degree. Its covariance is
R S S^T R^T with R the rotation matrix of the quaternion and S = diag(scale).
"""

from __future__ import annotations

import math

import torch
from scipy.spatial import cKDTree

from .sh import num_sh_bases

# Parameter names, in the order in which checkpoints and optimizers list them. They are gsplat's,
# with its conventions, so that gsplat's densification strategies can edit them: "scales" holds
# the logarithms of the scales and "opacities" the logits of the opacities.
PARAM_NAMES = ("means", "quats", "scales", "opacities", "sh0", "shN")

# 0th-order SH basis constant: a colour c maps to the DC coefficient (c - 0.5) / C0.
SH_C0 = 0.28209479177387814


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (...,3,3) of quaternions (...,4) in w, x, y, z order (normalized here)."""
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    rows = (
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    )
    return torch.stack(rows, dim=-1).reshape(*q.shape[:-1], 3, 3)


def covariance(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """Covariances R S S^T R^T, (...,3,3), of quaternions (...,4) and scales (...,3)."""
    M = quat_to_rotmat(quats) * scales[..., None, :]
    return M @ M.transpose(-1, -2)


def quats_facing(normals: torch.Tensor) -> torch.Tensor:
    """Unit quaternions (N,4) of the shortest rotations that take the z axis to `normals` (N,3):
    a Gaussian with them has its third axis along the normal."""
    n = normals / normals.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    # half-way quaternion (1 + z.n, z x n), normalized; z x n = (-n_y, n_x, 0)
    q = torch.stack([1 + n[:, 2], -n[:, 1], n[:, 0], torch.zeros_like(n[:, 0])], dim=-1)
    opposite = q[:, 0] < 1e-6  # n = -z: half a turn about x
    q[opposite] = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=q.dtype, device=q.device)
    return q / q.norm(dim=-1, keepdim=True)


def rgb_to_sh0(rgb: torch.Tensor) -> torch.Tensor:
    """The DC coefficient that evaluates to colour `rgb` (with the +0.5 offset of eval_sh)."""
    return (rgb - 0.5) / SH_C0


class Gaussians(torch.nn.Module):
    """A set of N Gaussians with spherical-harmonics colour of degree `sh_degree` (0 to 3).

    The parameters live in `self.params` (a ParameterDict keyed by PARAM_NAMES, the `params` of
    gsplat's strategy API) so that a densification strategy can replace them, row by row,
    together with the optimizer state.
    """

    def __init__(self, means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor,
                 opacity_logits: torch.Tensor, sh: torch.Tensor, sh_degree: int | None = None) -> None:
        super().__init__()
        k = sh.shape[1]
        degree = int(round(math.sqrt(k))) - 1 if sh_degree is None else int(sh_degree)
        if num_sh_bases(degree) != k:
            raise ValueError(f"sh has {k} coefficients per channel; degree {degree} needs {num_sh_bases(degree)}")
        n = means.shape[0]
        shapes = {"means": (means, (n, 3)), "quats": (quats, (n, 4)), "log_scales": (log_scales, (n, 3)),
                  "opacity_logits": (opacity_logits, (n,)), "sh": (sh, (n, k, 3))}
        for name, (value, shape) in shapes.items():
            if tuple(value.shape) != shape:
                raise ValueError(f"Gaussians.{name} has shape {tuple(value.shape)}, expected {shape}")
        self.sh_degree = degree
        P = torch.nn.Parameter
        self.params = torch.nn.ParameterDict({
            "means": P(means.detach().clone()),
            "quats": P(quats.detach().clone()),
            "scales": P(log_scales.detach().clone()),
            "opacities": P(opacity_logits.detach().clone()),
            "sh0": P(sh[:, :1].detach().clone()),
            "shN": P(sh[:, 1:].detach().clone()),
        })

    @classmethod
    def from_points(cls, points: torch.Tensor, colors: torch.Tensor | None = None, sh_degree: int = 3,
                    opacity: float = 0.1, scale: torch.Tensor | float | None = None) -> "Gaussians":
        """Isotropic Gaussians at `points` (N,3), sized by the distance to their 3 nearest neighbours.

        colors (N,3) in [0,1] set the DC term (grey when None); higher SH orders start at zero.
        """
        n = points.shape[0]
        dtype, device = points.dtype, points.device
        if scale is None:
            scale = nearest_neighbour_scale(points)
        scale = torch.as_tensor(scale, dtype=dtype, device=device).expand(n).clamp_min(1e-7)
        colors = torch.full((n, 3), 0.5, dtype=dtype, device=device) if colors is None else colors
        sh = torch.zeros(n, num_sh_bases(sh_degree), 3, dtype=dtype, device=device)
        sh[:, 0] = rgb_to_sh0(colors.to(dtype))
        quats = torch.zeros(n, 4, dtype=dtype, device=device)
        quats[:, 0] = 1
        logit = math.log(opacity / (1 - opacity))
        return cls(points, quats, scale.log()[:, None].expand(n, 3),
                   torch.full((n,), logit, dtype=dtype, device=device), sh, sh_degree)

    @classmethod
    def surfels(cls, points: torch.Tensor, normals: torch.Tensor, colors: torch.Tensor | None = None,
                sh_degree: int = 3, opacity: float = 0.5, thin: float = 3e-4) -> "Gaussians":
        """Flat Gaussians on a surface: discs at `points` (N,3) as wide as the distance to their
        neighbours, with their third axis `thin` (m) along `normals` (N,3) (see cap_scales)."""
        gaussians = cls.from_points(points, colors, sh_degree, opacity=opacity)
        with torch.no_grad():
            gaussians.params["quats"].copy_(quats_facing(normals.to(points.dtype)))
            gaussians.params["scales"][:, 2].clamp_(max=math.log(thin))
        return gaussians

    @torch.no_grad()
    def cap_scales(self, max_scale: float | None = None, thin: float | None = None) -> None:
        """Clamp every axis to `max_scale` and the third one (a surfel's normal) to `thin` (m)."""
        log_scales = self.params["scales"]
        if max_scale is not None:
            log_scales.clamp_(max=math.log(max_scale))
        if thin is not None:
            log_scales[:, 2].clamp_(max=math.log(thin))

    def __len__(self) -> int:
        return self.params["means"].shape[0]

    @property
    def means(self) -> torch.Tensor:
        return self.params["means"]

    @property
    def quats(self) -> torch.Tensor:
        return self.params["quats"]

    @property
    def scales(self) -> torch.Tensor:
        return self.params["scales"].exp()

    @property
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.params["opacities"])

    @property
    def sh(self) -> torch.Tensor:
        """SH coefficients (N, (degree+1)^2, 3)."""
        return torch.cat([self.params["sh0"], self.params["shN"]], dim=1)

    def covariances(self) -> torch.Tensor:
        return covariance(self.quats, self.scales)

    def tensors(self) -> dict[str, torch.Tensor]:
        """Detached copies of the raw parameters, keyed by PARAM_NAMES."""
        return {k: v.detach().clone() for k, v in self.params.items()}


def nearest_neighbour_scale(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """Root mean square distance of each point to its k nearest neighbours, (N,)."""
    pts = points.detach().cpu().double().numpy()
    if len(pts) <= 1:
        return torch.full((len(pts),), 0.01, dtype=points.dtype, device=points.device)
    k = min(k, len(pts) - 1)
    dist, _ = cKDTree(pts).query(pts, k=k + 1)
    rms = torch.from_numpy((dist[:, 1:] ** 2).mean(axis=1) ** 0.5)
    return rms.to(points.dtype).to(points.device)
