"""A small model pool from the asset library's pool split (never in a procedural world), for the appearance tests."""
from __future__ import annotations

from pathlib import Path


def small_pool(root: Path, assets=("box_truck-0020", "sedan-0045"), gaussians: int = 1500):
    """A pool at ``root`` holding one model per asset, built from its mesh with ``gaussians`` Gaussians."""
    from omniscs.agents.mesh import model_from_mesh
    from omniscs.agents.pool import Pool
    from omniscs.world.assets import build_asset

    p = Pool(root)
    for aid in assets:
        a = build_asset(aid)
        params, info = model_from_mesh(a.surface.vertices, a.surface.faces, a.surface.face_colour, gaussians, 0)
        p.add(params, a.category, "mesh", aid, info["quality_psnr"])
    return p
