"""Tile-based differentiable rasterization of 3D Gaussians in plain PyTorch.

`rasterize()` follows the tensor contract of gsplat's `rasterization()`: Gaussians (N,...) and a
batch of C pinhole cameras (world-to-camera 4x4 matrices and 3x3 intrinsics) give images
(C,H,W,D) and alphas (C,H,W,1). The steps are those of 3D Gaussian splatting:

1. EWA projection: each Gaussian's covariance is carried into the camera frame and through the
   Jacobian of the pinhole projection at its mean; a small isotropic term (eps2d, in pixels^2)
   keeps every splat at least about a pixel wide.
2. Screen extents: the axis-aligned box of the 3-sigma ellipse, half-widths 3 sqrt(cov_xx) and
   3 sqrt(cov_yy) pixels; a splat only ever touches pixels inside its 3-sigma ellipse.
3. Binning: every (Gaussian, tile) overlap becomes one entry with the key
   tile * (C N) + depth rank; a single torch.sort orders the entries by tile and then by depth.
4. Compositing, front to back, per pixel: alpha_i = min(0.999, o_i exp(-q_i / 2)), entries with
   alpha < 1/255 are skipped, and a pixel stops before the entry that would bring its
   transmittance to 1e-4 or below (the rules of the CUDA rasterizers).

Tiles are processed in chunks of similar list length; each chunk is padded to its longest list
and evaluated with dense tensor operations; its backward pass is written out (recomputing the
per-pixel terms from the chunk's inputs), so memory holds one chunk's per-pixel tensors at a time.
Everything runs on the device of the inputs (CPU or CUDA) and is differentiable through autograd.

Pixel centres sit at integer coordinates (OpenCV): pixel (i, j) is at x = i, y = j.
Unlike the CUDA rasterizers, whose splats also reach into pixels between 3 and about 3.3 sigma
when those happen to lie in a tile the splat overlaps, the cut-off here is the 3-sigma ellipse
itself, so the image does not depend on the tile size and a dense renderer reproduces it exactly.
"""

from __future__ import annotations

import math
from typing import Any

import torch

from .gaussians import covariance
from .sh import eval_sh

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.999
TRANSMITTANCE_MIN = 1e-4
SIGMA_CUTOFF = 4.5  # q / 2 at 3 sigma
EXP_FLOOR = -30.0  # -q / 2 is clamped here before exp (_splat_terms): far below -SIGMA_CUTOFF
FOV_CLAMP = 1.3  # the Jacobian is taken no further out than 1.3 times the half field of view
EPS2D = 0.3  # 3DGS's splat blur (pixels^2): no splat is drawn thinner than about a pixel


def unpack_covars(covars: torch.Tensor) -> torch.Tensor:
    """Covariances (N,3,3) from (N,3,3) or the packed upper triangle (N,6) xx, xy, xz, yy, yz, zz."""
    if covars.shape[-2:] == (3, 3):
        return covars
    if covars.shape[-1] != 6:
        raise ValueError(f"covars must be (N,3,3) or (N,6), got {tuple(covars.shape)}")
    xx, xy, xz, yy, yz, zz = covars.unbind(-1)
    rows = (xx, xy, xz, xy, yy, yz, xz, yz, zz)
    return torch.stack(rows, dim=-1).reshape(*covars.shape[:-1], 3, 3)


def project(means: torch.Tensor, covars: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor,
            width: int, height: int, near_plane: float = 0.01, far_plane: float = 1e10,
            eps2d: float = EPS2D) -> dict[str, torch.Tensor]:
    """EWA projection of N Gaussians into C cameras: means (N,3) and covars (N,3,3), or per camera
    (C,N,3) and (C,N,3,3) (e.g. a posed hand, one pose per camera).

    Returns means2d (C,N,2) pixels, conics (C,N,3) = the inverse 2D covariance as (a, b, c) of
    [[a, b], [b, c]], depths (C,N) camera z, extents (C,N,2) 3-sigma half-widths in pixels, and
    valid (C,N): in front of the near plane, before the far plane, with a positive-definite
    2D covariance.
    """
    R = viewmats[:, :3, :3]
    t = viewmats[:, :3, 3]
    xc = torch.einsum("cij,nj->cni" if means.dim() == 2 else "cij,cnj->cni", R, means) + t[:, None, :]
    x, y, z = xc.unbind(-1)
    valid = (z > near_plane) & (z < far_plane)
    z = torch.where(valid, z, torch.ones_like(z))  # keeps culled entries finite for autograd

    fx, skew, cx = Ks[:, 0, 0, None], Ks[:, 0, 1, None], Ks[:, 0, 2, None]
    fy, cy = Ks[:, 1, 1, None], Ks[:, 1, 2, None]
    xn, yn = x / z, y / z
    means2d = torch.stack([fx * xn + skew * yn + cx, fy * yn + cy], dim=-1)

    # Far outside the image the linearization is poor and blows splats up; clamp where it is taken.
    margin_x, margin_y = (FOV_CLAMP - 1) * 0.5 * width / fx, (FOV_CLAMP - 1) * 0.5 * height / fy
    xj = torch.minimum(torch.maximum(xn, -cx / fx - margin_x), (width - cx) / fx + margin_x)
    yj = torch.minimum(torch.maximum(yn, -cy / fy - margin_y), (height - cy) / fy + margin_y)
    zero = torch.zeros_like(z)
    J = torch.stack([
        torch.stack([fx / z, skew / z, -(fx * xj + skew * yj) / z], dim=-1),
        torch.stack([zero, fy / z, -fy * yj / z], dim=-1),
    ], dim=-2)  # (C,N,2,3)
    M = J @ R[:, None]  # world -> pixel Jacobian
    cov2d = M @ (covars[None] if covars.dim() == 3 else covars) @ M.transpose(-1, -2)
    a = cov2d[..., 0, 0] + eps2d
    b = cov2d[..., 0, 1]
    c = cov2d[..., 1, 1] + eps2d
    det = a * c - b * b
    valid = valid & (det > 0)
    det = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([c / det, -b / det, a / det], dim=-1)
    extents = 3.0 * torch.stack([a, c], dim=-1).detach().clamp_min(0).sqrt()
    return {"means2d": means2d, "conics": conics, "depths": xc[..., 2], "extents": extents, "valid": valid}


@torch.no_grad()
def bin_gaussians(means2d: torch.Tensor, extents: torch.Tensor, depths: torch.Tensor, valid: torch.Tensor,
                  width: int, height: int, tile_size: int) -> dict[str, torch.Tensor]:
    """Every (Gaussian, tile) overlap, sorted by tile and then depth with one torch.sort.

    Returns gaussian_ids (M,) flat indices c * N + n in drawing order, tile_offsets and
    tile_counts (C * tiles_y * tiles_x,) into them, and visible (C,N): the splat reaches a pixel.
    """
    C, N = depths.shape
    device = depths.device
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    n_tiles = tiles_x * tiles_y
    # The pixel range inside the 3-sigma box; a hair of slack so that rounding never drops a
    # pixel that the compositing test keeps.
    lo = torch.ceil(means2d - extents - 1e-4)
    hi = torch.floor(means2d + extents + 1e-4)
    lo = torch.maximum(lo, torch.zeros_like(lo))
    hi = torch.minimum(hi, torch.tensor([width - 1.0, height - 1.0], device=device, dtype=hi.dtype))
    valid = valid & (lo <= hi).all(dim=-1)
    lo_t = torch.div(lo.clamp(0, 1 << 30), tile_size, rounding_mode="floor").long()
    hi_t = torch.div(hi.clamp(0, 1 << 30), tile_size, rounding_mode="floor").long()
    span = hi_t - lo_t + 1
    counts = torch.where(valid, span[..., 0] * span[..., 1], 0).reshape(-1)

    flat = torch.nonzero(counts).squeeze(1)
    per = counts[flat]
    total = int(per.sum())
    gaussian_ids = torch.repeat_interleave(flat, per)
    first = torch.cumsum(per, 0) - per
    local = torch.arange(total, device=device) - torch.repeat_interleave(first, per)
    row_len = torch.repeat_interleave(span[..., 0].reshape(-1)[flat], per)
    tx = lo_t[..., 0].reshape(-1)[gaussian_ids] + local % row_len
    ty = lo_t[..., 1].reshape(-1)[gaussian_ids] + torch.div(local, row_len, rounding_mode="floor")
    tile = torch.div(gaussian_ids, N, rounding_mode="floor") * n_tiles + ty * tiles_x + tx

    # Depth rank over all cameras at once: ranks within one camera keep their order.
    rank = torch.empty(C * N, dtype=torch.long, device=device)
    rank[torch.argsort(depths.reshape(-1))] = torch.arange(C * N, device=device)
    keys, order = torch.sort(tile * (C * N) + rank[gaussian_ids])
    tile_sorted = torch.div(keys, C * N, rounding_mode="floor")
    tile_counts = torch.bincount(tile_sorted, minlength=C * n_tiles)
    tile_offsets = torch.cumsum(tile_counts, 0) - tile_counts
    return {"gaussian_ids": gaussian_ids[order], "tile_offsets": tile_offsets, "tile_counts": tile_counts,
            "tiles_x": torch.tensor(tiles_x), "tiles_y": torch.tensor(tiles_y), "visible": valid}


def quadratic_coefficients(m: torch.Tensor, con: torch.Tensor) -> torch.Tensor:
    """q/2 of splats as a quadratic polynomial in pixel coordinates, (...,6).

    For centres m (...,2) and conics (a, b, c) (...,3), in coordinates relative to a tile's
    centre: q/2 = k . (x^2, y^2, x y, x, y, 1). Evaluating every splat at every pixel of a tile
    is then one matrix product with the tile's fixed basis (P,6) instead of a dozen elementwise
    passes; tile-centred coordinates keep the terms small enough for float32.
    """
    a, b, c = con.unbind(-1)
    mx, my = m.unbind(-1)
    return torch.stack([0.5 * a, 0.5 * c, b, -(a * mx + b * my), -(c * my + b * mx),
                        0.5 * a * mx * mx + 0.5 * c * my * my + b * mx * my], dim=-1)


def _mask(op, a: torch.Tensor, b) -> torch.Tensor:
    """op(a, b) as 0.0/1.0 in a's dtype.

    Float masks multiply into the chunk tensors; on the CPU, comparisons written straight into a
    float tensor and in-place products are several times faster than boolean masks with
    torch.where (which otherwise dominate the compositing time). Binary operations keep the
    full-size tensor first: broadcasting the first operand takes a slow path in TensorIterator.
    """
    return op(a, b, out=torch.empty_like(a))


def _splat_terms(coeffs: torch.Tensor, op: torch.Tensor, basis: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Per (tile, pixel, entry) quantities of a padded chunk, shared by forward and backward.

    coeffs (T,L,6), op (T,L) (zero on padding), basis (P,6). Returns the Gaussian factor
    g = exp(-q/2), alpha as drawn (zero where skipped or after the pixel stopped), 1 - alpha,
    the mask of drawn entries, the transmittance before each entry and the final transmittance
    (T,P).
    """
    # Clamped first: on the CPU, exp of an argument below about -88 (a result under float32's
    # smallest normal) leaves the vectorized path and costs some 30 times more, and most entries
    # lie far outside their splat. Nothing below exp(-4.5) is drawn, so no drawn value changes.
    g = torch.matmul(basis, coeffs.transpose(1, 2)).neg_().clamp_min_(EXP_FLOOR).exp_()  # (T,P,L)
    # Inside the 3-sigma ellipse (g >= e^-4.5) and alpha = o g >= 1/255, in one comparison;
    # padding has o = 0 and so an infinite bound.
    bound = torch.maximum(torch.full_like(op, math.exp(-SIGMA_CUTOFF)), ALPHA_MIN / op)
    drawn = _mask(torch.ge, g, bound[:, None, :])
    alpha = (g * op[:, None, :]).clamp_max_(ALPHA_MAX).mul_(drawn)
    # Transmittance only falls along a list, so "stop before the entry that would reach 1e-4"
    # keeps exactly the entries whose inclusive product stays above it: a prefix of the list.
    one_minus = 1 - alpha  # past the prefix not 1 - alpha as drawn, but only read where drawn
    reach = torch.cumprod(one_minus, dim=-1)
    prefix = _mask(torch.gt, reach, TRANSMITTANCE_MIN)
    drawn.mul_(prefix)
    alpha.mul_(prefix)
    before = torch.cat([torch.ones_like(reach[..., :1]), reach[..., :-1]], dim=-1)
    n_prefix = prefix.sum(-1, keepdim=True).long()
    final = torch.where(n_prefix > 0, reach.gather(-1, (n_prefix - 1).clamp_min(0)), 1.0).squeeze(-1)
    return g, alpha, one_minus, drawn, before, final


class _Composite(torch.autograd.Function):
    """Front-to-back compositing of a chunk of T tiles with a hand-written backward.

    Inputs: the chunk's splats as quadratic coefficients (T,L,6), opacities (T,L) and colours
    (T,L,D), and the pixel basis (P,6). Outputs colour (T,P,D) and alpha (T,P). Only the inputs
    are saved; the backward recomputes the per-pixel terms, so memory stays at one chunk, and
    uses the closed form of the compositing derivative: dC/dalpha_i = T_i c_i -
    (sum_{k>i} w_k c_k) / (1 - alpha_i) and dA/dalpha_i = T_final / (1 - alpha_i).
    """

    @staticmethod
    def forward(ctx, coeffs, op, col, basis):
        _, alpha, _, _, before, final = _splat_terms(coeffs, op, basis)
        ctx.save_for_backward(coeffs, op, col, basis)
        # (col^T w^T)^T rather than w col: MKL's batched GEMM is far faster with the small
        # colour dimension on the outside (here and in the backward products below).
        return torch.bmm(col.transpose(1, 2), alpha.mul_(before).transpose(1, 2)).transpose(1, 2), 1 - final

    @staticmethod
    def backward(ctx, d_color, d_alpha):
        coeffs, op, col, basis = ctx.saved_tensors
        g, alpha, one_minus, drawn, before, final = _splat_terms(coeffs, op, basis)
        weights = alpha * before
        d_col = torch.bmm(d_color.transpose(1, 2), weights).transpose(1, 2)  # (T,L,D)
        proj = torch.bmm(d_color, col.transpose(1, 2))  # c_i . dC, (T,P,L)
        wc = weights.mul_(proj)
        # sum over k > i of w_k c_k . dC, minus the alpha output's share dA * T_final
        later = torch.cumsum(wc, dim=-1).neg_().add_(wc.sum(-1, keepdim=True))
        later.sub_((d_alpha * final)[..., None]).div_(one_minus)
        d_a = before.mul_(proj).sub_(later)
        # alpha = min(o g, 0.999): no gradient where it is clamped
        live = drawn.mul_(_mask(torch.lt, g, ALPHA_MAX / op[:, None, :]))
        dg = d_a.mul_(live).mul_(g)
        d_op = dg.sum(1)
        d_coeffs = -torch.matmul(basis.T, dg.mul_(op[:, None, :])).transpose(1, 2)  # (T,L,6)
        return d_coeffs, d_op, d_col, None


def _chunks(counts: torch.Tensor, pixels_per_tile: int, budget: int) -> list[tuple[int, int]]:
    """Split tiles sorted by ascending list length into runs whose padded size fits `budget`.

    A run i..j costs (j - i + 1) * counts[j] * pixels; the cost grows with j, so each run's end is
    one searchsorted away and the loop is over chunks, not tiles.
    """
    n = counts.numel()
    limit = max(budget // pixels_per_tile, 1)
    cpu = counts.cpu()
    out, i = [], 0
    while i < n:
        cost = (torch.arange(n - i) + 1) * cpu[i:]
        j = i + max(int(torch.searchsorted(cost, torch.tensor(limit), right=True)), 1)
        out.append((i, j))
        i = j
    return out


def rasterize_tiles(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, colors: torch.Tensor,
                    bins: dict[str, torch.Tensor], n_cameras: int, width: int, height: int, tile_size: int,
                    chunk_elements: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite binned splats: flat per-(camera, Gaussian) tensors (C*N, ...) -> colour
    (C*H*W, D) and alpha (C*H*W,) without background."""
    device = means2d.device
    D = colors.shape[-1]
    tiles_x = int(bins["tiles_x"])
    n_tiles = tiles_x * int(bins["tiles_y"])
    counts = bins["tile_counts"]
    active = torch.nonzero(counts).squeeze(1)
    by_len = torch.argsort(counts[active])
    active = active[by_len]
    active_counts = counts[active]

    P = tile_size * tile_size
    local = torch.arange(P, device=device)
    local_xy = torch.stack([local % tile_size, torch.div(local, tile_size, rounding_mode="floor")], dim=-1)
    half = (tile_size - 1) / 2
    x, y = (local_xy.to(means2d.dtype) - half).unbind(-1)
    basis = torch.stack([x * x, y * y, x * y, x, y, torch.ones_like(x)], dim=-1)  # (P,6)
    colors_out, alphas_out, pixel_ids = [], [], []
    for i, j in _chunks(active_counts, P, chunk_elements):
        tiles = active[i:j]
        L = int(active_counts[j - 1])
        slot = torch.arange(L, device=device)
        present = slot[None, :] < counts[tiles][:, None]
        index = (bins["tile_offsets"][tiles][:, None] + slot[None, :]).clamp_max(bins["gaussian_ids"].numel() - 1)
        gids = bins["gaussian_ids"][index]
        cam = torch.div(tiles, n_tiles, rounding_mode="floor")
        in_cam = tiles - cam * n_tiles
        origin = torch.stack([in_cam % tiles_x, torch.div(in_cam, tiles_x, rounding_mode="floor")], dim=-1) * tile_size
        coeffs = quadratic_coefficients(means2d[gids] - (origin[:, None, :] + half).to(means2d.dtype), conics[gids])
        op = torch.where(present, opacities[gids], 0.0)
        color, alpha = _Composite.apply(coeffs, op, colors[gids], basis)
        pxy = origin[:, None, :] + local_xy[None]  # (T,P,2)
        inside = (pxy[..., 0] < width) & (pxy[..., 1] < height)
        flat = cam[:, None] * (width * height) + pxy[..., 1] * width + pxy[..., 0]
        colors_out.append(color[inside])
        alphas_out.append(alpha[inside])
        pixel_ids.append(flat[inside])
    # Empty slices of every input keep the outputs in the autograd graph when nothing is visible.
    anchor = opacities[:0] + means2d[:0].sum(-1) + conics[:0].sum(-1)
    colors_out.append(colors[:0] + anchor[:, None])
    alphas_out.append(anchor)
    pixel_ids.append(torch.zeros(0, dtype=torch.long, device=device))
    total = n_cameras * width * height
    ids = torch.cat(pixel_ids)
    out_color = torch.zeros(total, D, dtype=colors.dtype, device=device).index_copy(0, ids, torch.cat(colors_out))
    out_alpha = torch.zeros(total, dtype=colors.dtype, device=device).index_copy(0, ids, torch.cat(alphas_out))
    return out_color, out_alpha


def drawn(radii: torch.Tensor) -> torch.Tensor:
    """(C,N) bool: the splats that reach a pixel, from radii (C,N,2), or (C,N) as older gsplat gives."""
    return (radii > 0).all(-1) if radii.dim() == 3 else radii > 0


def gsplat_available() -> bool:
    """True when the optional gsplat package imports (it needs CUDA to rasterize)."""
    try:
        import gsplat  # noqa: F401
    except Exception:  # a broken CUDA build raises more than ImportError
        return False
    return True


def _per_camera(x: torch.Tensor, C: int, N: int, name: str, tail: int) -> torch.Tensor:
    """(N, ...) or (C, N, ...) -> (C, N, ...)."""
    if x.dim() == tail + 1 and x.shape[0] == N:
        return x.unsqueeze(0).expand(C, *x.shape)
    if x.dim() == tail + 2 and x.shape[:2] == (C, N):
        return x
    raise ValueError(f"{name} has shape {tuple(x.shape)}; expected ({N}, ...) or ({C}, {N}, ...)")


def rasterize(means: torch.Tensor, quats: torch.Tensor | None, scales: torch.Tensor | None,
              opacities: torch.Tensor, colors: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor,
              width: int, height: int, background: torch.Tensor | None = None,
              covars: torch.Tensor | None = None, sh_degree: int | None = None,
              near_plane: float = 0.01, far_plane: float = 1e10, eps2d: float = EPS2D, tile_size: int = 8,
              backend: str = "auto", chunk_elements: int | None = None, return_meta: bool = False):
    """Render N Gaussians into C cameras: (rgb (C,H,W,D), alpha (C,H,W,1)) [, meta].

    means (N,3), or (C,N,3) with covars (C,N,3,3): one set of centres per camera (the views of
    several poses of an articulated model in one call); quats (N,4) w x y z, any norm; scales (N,3)
    (not log); opacities (N,) or (C,N) in [0,1]; colors (N,D) or (C,N,D) values, or with
    `sh_degree` SH coefficients (N,K,3) or (C,N,K,3); viewmats (C,4,4) world-to-camera
    (x_cam = R x + t); Ks (C,3,3) in pixels with pixel centres at integer coordinates; background
    (D,) or (C,D) composited behind, black when None. covars (N,3,3) or packed (N,6) replace quats
    and scales.

    backend: "torch" (this module), "gsplat" (CUDA only) or "auto" (gsplat when it is installed
    and the inputs are on a CUDA device). chunk_elements bounds tiles x pixels x list length per
    compositing chunk, hence peak memory (default 2^18 on the CPU, where chunks that fit the
    caches are fastest, 2^25 on CUDA). The default tile of 8x8 pixels (gsplat: 16x16) wastes
    less work on small splats; the image does not depend on it. With return_meta, meta holds what
    gsplat's `rasterization` returns for its densification strategies: means2d (C,N,2; call
    retain_grad() on it for their statistics), radii (C,N,2) integer 3-sigma half-widths in pixels
    (0: not drawn), width, height, n_cameras and gaussian_ids (None: not packed); and depths,
    conics, visible (C,N) and n_isects.
    """
    C, N = viewmats.shape[0], means.shape[-2]
    if means.dim() == 3 and (means.shape[0] != C or covars is None):
        raise ValueError(f"per-camera means {tuple(means.shape)} need one row per camera ({C}) and covars")
    if viewmats.shape != (C, 4, 4) or Ks.shape != (C, 3, 3):
        raise ValueError(f"viewmats must be (C,4,4) and Ks (C,3,3); got {tuple(viewmats.shape)}, {tuple(Ks.shape)}")
    if backend == "auto":
        backend = "gsplat" if means.is_cuda and gsplat_available() else "torch"
    if backend == "gsplat":
        if not (means.is_cuda and gsplat_available()):
            raise RuntimeError("the gsplat backend needs the gsplat package and inputs on a CUDA device; "
                               "use backend='torch' (or 'auto')")
        return _rasterize_gsplat(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                                 background, covars, sh_degree, near_plane, far_plane, eps2d, return_meta)
    if backend != "torch":
        raise ValueError(f"unknown backend {backend!r} (torch, gsplat or auto)")

    covars = covariance(quats, scales) if covars is None else unpack_covars(covars)
    proj = project(means, covars, viewmats, Ks, width, height, near_plane, far_plane, eps2d)
    if sh_degree is None:
        cols = _per_camera(colors, C, N, "colors", 1)
    else:
        coeffs = _per_camera(colors, C, N, "SH colors", 2)
        R, t = viewmats[:, :3, :3], viewmats[:, :3, 3]
        centres = -torch.einsum("cji,cj->ci", R, t)
        cols = eval_sh(sh_degree, coeffs, (means[None] if means.dim() == 2 else means) - centres[:, None])
    opac = _per_camera(opacities, C, N, "opacities", 0)
    D = cols.shape[-1]

    if chunk_elements is None:
        chunk_elements = 1 << 25 if means.is_cuda else 1 << 18
    bins = bin_gaussians(proj["means2d"].detach(), proj["extents"], proj["depths"].detach(), proj["valid"],
                         width, height, tile_size)
    color, alpha = rasterize_tiles(proj["means2d"].reshape(C * N, 2), proj["conics"].reshape(C * N, 3),
                                   opac.reshape(C * N), cols.reshape(C * N, D), bins, C, width, height,
                                   tile_size, chunk_elements)
    rgb = color.reshape(C, height, width, D)
    alpha = alpha.reshape(C, height, width, 1)
    if background is not None:
        bg = background.expand(C, D) if background.dim() == 1 else background
        rgb = rgb + (1 - alpha) * bg[:, None, None, :]
    if not return_meta:
        return rgb, alpha
    meta: dict[str, Any] = {
        "means2d": proj["means2d"], "conics": proj["conics"], "depths": proj["depths"],
        "visible": bins["visible"],
        "radii": torch.where(bins["visible"][..., None], proj["extents"].ceil(), 0).long(),
        "n_isects": int(bins["gaussian_ids"].numel()), "width": width, "height": height, "n_cameras": C,
        "gaussian_ids": None,
    }
    return rgb, alpha, meta


def _rasterize_gsplat(means, quats, scales, opacities, colors, viewmats, Ks, width, height, background,
                      covars, sh_degree, near_plane, far_plane, eps2d, return_meta):
    """The same call on gsplat's CUDA kernels (pixel centres shifted to gsplat's half-integers;
    gsplat's own 16x16 tiles, the size its kernels are tuned for)."""
    import gsplat  # optional, and CUDA only: imported where it is used

    C = viewmats.shape[0]
    Ks = Ks.clone()
    Ks[:, :2, 2] += 0.5
    if covars is not None:
        covars = unpack_covars(covars)
    backgrounds = None
    if background is not None:
        backgrounds = background.expand(C, background.shape[-1]) if background.dim() == 1 else background
    batched = means.dim() == 3  # per-camera centres: gsplat's batch axis, one camera per batch
    if batched:
        viewmats, Ks = viewmats[:, None], Ks[:, None]
        opacities = opacities.expand(C, -1) if opacities.dim() == 1 else opacities
        colors = colors.expand(C, *colors.shape) if colors.dim() == (2 if sh_degree is None else 3) else colors
        backgrounds = None if backgrounds is None else backgrounds[:, None]
    rgb, alpha, meta = gsplat.rasterization(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane=near_plane,
        far_plane=far_plane, eps2d=eps2d, sh_degree=sh_degree, tile_size=16, backgrounds=backgrounds,
        covars=covars, packed=False)
    if batched:
        rgb, alpha = rgb[:, 0], alpha[:, 0]
        meta = {k: v[:, 0] if torch.is_tensor(v) and v.dim() >= 3 and v.shape[1] == 1 else v for k, v in meta.items()}
    if not return_meta:
        return rgb, alpha
    meta["visible"] = drawn(meta["radii"])
    meta["n_cameras"] = C
    return rgb, alpha, meta
