"""The bundled PyTorch Gaussian splatting trainer (the reconstruction backend).

`rasterize` renders Gaussians with gsplat's tensor contract; the rest of the package builds the
object and MANUS-Hand models on top of it. See docs/splat.md.
"""

from .rasterize import rasterize

__all__ = ["rasterize"]
