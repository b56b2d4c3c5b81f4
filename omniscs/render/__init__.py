"""Differentiable Gaussian rasterisation (EWA splatting) with gsplat's API: reference, CPU and gsplat backends."""
from omniscs.render.api import BACKENDS, RENDER_MODES, rasterize

__all__ = ["BACKENDS", "RENDER_MODES", "rasterize"]
