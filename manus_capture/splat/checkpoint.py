"""Checkpoints of Gaussian models: one safetensors file, tensors and string metadata only.

Format (version 1), all tensors float32 unless noted:

    means (N,3)            Gaussian centres (object: world frame; hand: canonical hand frame)
    quats (N,4)            rotations, w x y z (not necessarily normalized)
    log_scales (N,3)       natural log of the scales
    opacity_logits (N,)    logit of the opacities
    sh0 (N,1,3)            degree-0 SH coefficient per colour channel
    shN (N,K-1,3)          higher SH coefficients, K = (sh_degree + 1)^2
    ...                    model-specific tensors (the hand adds skin_grid (20,G,G,G),
                           grid_min (3,), grid_max (3,), bone_lengths (20,))

    metadata: format = "manus-capture-splat", version = "1", kind = "object" | "hand",
              sh_degree = "0".."3", plus free-form string fields (e.g. the calibration used).

safetensors never executes code on load, unlike a pickle; the file is written atomically.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from safetensors import safe_open
from safetensors.torch import save

from manus_core.errors import CheckpointError
from manus_core.fileio import write_atomic

from .gaussians import PARAM_NAMES, Gaussians

FORMAT = "manus-capture-splat"
VERSION = "1"
# The file names what the tensors hold; in memory the parameters carry gsplat's names.
FILE_NAMES = {"scales": "log_scales", "opacities": "opacity_logits"}
PARAM_FILE_NAMES = tuple(FILE_NAMES.get(name, name) for name in PARAM_NAMES)


def save_checkpoint(path: str | os.PathLike, gaussians: Gaussians, kind: str = "object",
                    extra: dict[str, torch.Tensor] | None = None, metadata: dict[str, str] | None = None) -> None:
    """Write the model (and `extra` tensors, e.g. the hand's skinning grid) to `path` atomically."""
    tensors = {FILE_NAMES.get(k, k): v.detach().to("cpu", torch.float32).contiguous()
               for k, v in gaussians.tensors().items()}
    for name, value in (extra or {}).items():
        if name in tensors:
            raise ValueError(f"extra tensor {name!r} would overwrite a Gaussian parameter")
        tensors[name] = value.detach().cpu().contiguous()
    meta = {str(k): str(v) for k, v in (metadata or {}).items()}
    meta.update(format=FORMAT, version=VERSION, kind=kind, sh_degree=str(gaussians.sh_degree))
    write_atomic(path, save(tensors, metadata=meta))


def load_checkpoint(path: str | os.PathLike, device: str | torch.device = "cpu"
                    ) -> tuple[Gaussians, dict[str, torch.Tensor], dict[str, str]]:
    """(gaussians, extra tensors, metadata) from a checkpoint written by save_checkpoint."""
    path = Path(path)
    try:
        with safe_open(str(path), framework="pt", device=str(device)) as f:
            meta = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except FileNotFoundError:
        raise CheckpointError(f"{path}: no such checkpoint") from None
    except Exception as exc:  # safetensors raises its own error types for a damaged header
        raise CheckpointError(f"{path}: not a safetensors checkpoint ({exc})") from None
    if meta.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a manus-capture splat checkpoint (format {meta.get('format')!r})")
    if meta.get("version") != VERSION:
        raise CheckpointError(f"{path}: checkpoint version {meta.get('version')!r}, this software reads {VERSION}")
    missing = [k for k in PARAM_FILE_NAMES if k not in tensors]
    if missing:
        raise CheckpointError(f"{path}: checkpoint lacks {', '.join(missing)}")
    sh = torch.cat([tensors["sh0"], tensors["shN"]], dim=1)
    try:
        gaussians = Gaussians(tensors["means"], tensors["quats"], tensors["log_scales"], tensors["opacity_logits"],
                              sh, int(meta.get("sh_degree", -1)))
    except ValueError as exc:
        raise CheckpointError(f"{path}: {exc}") from None
    extra = {k: v for k, v in tensors.items() if k not in PARAM_FILE_NAMES}
    return gaussians, extra, meta
