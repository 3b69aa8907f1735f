"""Cameras for synthetic scenes: what the tests and benchmarks of the splatting code render known
models into (the simulated cube is for everything that needs real takes)."""

from __future__ import annotations

import torch


def look_at(eye: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """World-to-camera (4,4) of a camera at `eye` looking at `target`, z up in the world
    (x_cam = R x + t; the camera's y axis points down the image)."""
    z = (target - eye) / (target - eye).norm()
    x = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0], dtype=z.dtype), z)
    x = x / x.norm()
    R = torch.stack([x, torch.linalg.cross(z, x), z])
    V = torch.eye(4, dtype=z.dtype)
    V[:3, :3], V[:3, 3] = R, -R @ eye
    return V
