"""A dense brute-force Gaussian renderer, the yardstick for `rasterize` in the tests.

Every Gaussian is evaluated at every pixel and the pixels composite the Gaussians one by one in
depth order, with no tiles, no sorting keys and no chunking. The model is the same as the
rasterizer's (EWA splats with eps2d, the 3-sigma ellipse cut-off, alpha clamped to 0.999 and
skipped below 1/255, early stop at transmittance 1e-4), but it is derived independently: the
rotation comes from the quaternion's axis and angle (Rodrigues), the projection's Jacobian from
autograd of the pinhole map, and the conic from a matrix inverse. It costs O(C H W N) and is
meant for scenes of a few dozen Gaussians.
"""

from __future__ import annotations

import torch

from .rasterize import ALPHA_MAX, ALPHA_MIN, FOV_CLAMP, SIGMA_CUTOFF, TRANSMITTANCE_MIN


def _rodrigues(quats: torch.Tensor) -> torch.Tensor:
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, v = q[:, 0], q[:, 1:]
    s = v.norm(dim=-1)
    angle = 2 * torch.atan2(s, w)
    axis = v / s.clamp_min(1e-30)[:, None]
    Kx = torch.zeros(len(q), 3, 3, dtype=q.dtype)
    Kx[:, 0, 1], Kx[:, 0, 2], Kx[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    Kx = Kx - Kx.transpose(1, 2)
    eye = torch.eye(3, dtype=q.dtype).expand(len(q), 3, 3)
    return eye + torch.sin(angle)[:, None, None] * Kx + (1 - torch.cos(angle))[:, None, None] * Kx @ Kx


def render_reference(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                     colors: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                     background: torch.Tensor | None = None, near_plane: float = 0.01,
                     eps2d: float = 0.3) -> tuple[torch.Tensor, torch.Tensor]:
    """Images (C,H,W,D) and alphas (C,H,W,1) of Gaussians with plain colours (N,D); no autograd."""
    means, quats, scales, opacities, colors = (x.detach() for x in (means, quats, scales, opacities, colors))
    Rg = _rodrigues(quats)
    cov3 = Rg @ torch.diag_embed(scales ** 2) @ Rg.transpose(1, 2)
    ys, xs = torch.meshgrid(torch.arange(height, dtype=means.dtype), torch.arange(width, dtype=means.dtype),
                            indexing="ij")
    pixels = torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=-1)  # (P,2)
    rgbs, alphas = [], []
    for c in range(viewmats.shape[0]):
        R, t, K = viewmats[c, :3, :3], viewmats[c, :3, 3], Ks[c]

        def pinhole(p: torch.Tensor) -> torch.Tensor:
            h = K @ p
            return h[:2] / h[2]

        pc = means @ R.T + t
        z = pc[:, 2]
        f, cxy = K.diagonal()[:2], K[:2, 2]
        size = torch.tensor([width, height], dtype=means.dtype)
        margin = (FOV_CLAMP - 1) * 0.5 * size / f
        lim_lo, lim_hi = -cxy / f - margin, (size - cxy) / f + margin
        xy = torch.minimum(torch.maximum(pc[:, :2] / z[:, None], lim_lo), lim_hi)
        at = torch.cat([xy * z[:, None], z[:, None]], dim=-1)
        J = torch.func.vmap(torch.func.jacrev(pinhole))(at)  # (N,2,3)
        cov2 = J @ R @ cov3 @ R.T @ J.transpose(1, 2) + eps2d * torch.eye(2, dtype=means.dtype)
        centre = torch.func.vmap(pinhole)(pc)
        ok = (z > near_plane) & (torch.linalg.det(cov2) > 0)
        inv = torch.linalg.inv(torch.where(ok[:, None, None], cov2, torch.eye(2, dtype=means.dtype)))

        d = pixels[:, None, :] - centre[None]  # (P,N,2)
        q = torch.einsum("pni,nij,pnj->pn", d, inv, d)
        alpha = torch.clamp_max(opacities[None] * torch.exp(-0.5 * q), ALPHA_MAX)
        alpha = torch.where(ok[None] & (0.5 * q <= SIGMA_CUTOFF) & (alpha >= ALPHA_MIN), alpha, 0.0)

        T = torch.ones(len(pixels), dtype=means.dtype)
        done = torch.zeros(len(pixels), dtype=torch.bool)
        rgb = torch.zeros(len(pixels), colors.shape[-1], dtype=means.dtype)
        for n in torch.argsort(z).tolist():
            a = alpha[:, n]
            nxt = T * (1 - a)
            done = done | (nxt <= TRANSMITTANCE_MIN)
            draw = ~done
            rgb = rgb + torch.where(draw, a * T, 0.0)[:, None] * colors[n]
            T = torch.where(draw, nxt, T)
        if background is not None:
            bg = background if background.dim() == 1 else background[c]
            rgb = rgb + T[:, None] * bg
        rgbs.append(rgb.reshape(height, width, -1))
        alphas.append((1 - T).reshape(height, width, 1))
    return torch.stack(rgbs), torch.stack(alphas)
