"""Pool models from meshes: flat Gaussians on the surface that look like the mesh from every side (better after
refinement, on views they were not refined on), keyframes all around, clear errors for bad meshes, and the
``pool build`` command over the asset library."""
from __future__ import annotations

import numpy as np
import pytest

from omniscs.agents.mesh import (gaussians_from_mesh, keyframes, model_from_mesh, orbit_cameras, raycast_views,
                                 view_psnr)
from omniscs.errors import ValidationError


@pytest.fixture(scope="module")
def sedan():
    from omniscs.world.assets import build_asset

    return build_asset("sedan-0005")


def test_gaussians_lie_flat_on_the_surface_with_the_mesh_colours(sedan):
    s = sedan.surface
    g = gaussians_from_mesh(s.vertices, s.faces, s.face_colour, n=3000)
    means = g.means.numpy()
    assert len(g) == 3000 and np.all(np.abs(means) <= sedan.size / 2 + 1e-4)
    scales = np.sort(np.exp(g.log_scales.numpy()), 1)
    assert np.all(scales[:, 0] < 0.2 * scales[:, 1])  # one thin axis: flat


def test_the_model_looks_like_the_mesh_from_views_it_was_not_refined_on(sedan):
    s = sedan.surface
    params, info = model_from_mesh(s.vertices, s.faces, s.face_colour, n=8000, refine_steps=40)
    held = orbit_cameras(sedan.size, 8, elevation_deg=45.0)
    rgb, alpha = raycast_views(s.vertices, s.faces, s.face_colour, held)
    raw = gaussians_from_mesh(s.vertices, s.faces, s.face_colour, n=8000)
    assert view_psnr(params, rgb, alpha, held) > view_psnr(raw, rgb, alpha, held) > 15.0
    assert info["quality_psnr"] > 15.0 and info["seconds"] < 30.0
    k = keyframes(params, sedan.size)
    assert k.shape == (30, 96, 96, 4) and k.dtype == np.uint8
    covered = (k[..., 3] > 128).mean((1, 2))
    assert covered.min() > 0.05  # the car is in every keyframe
    assert covered[0] < covered[7]  # seen from the front it is narrower than from the side (84 degrees)


def test_bad_meshes_are_clear_errors():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    with pytest.raises(ValidationError, match="at least one triangle"):
        gaussians_from_mesh(v, np.zeros((0, 3), int), np.zeros((0, 3)))
    with pytest.raises(ValidationError, match="do not exist"):
        gaussians_from_mesh(v, [[0, 1, 5]], [[0.5, 0.5, 0.5]])
    with pytest.raises(ValidationError, match="finite"):
        gaussians_from_mesh(v, [[0, 1, 2]], [[np.nan, 0.5, 0.5]])
    with pytest.raises(ValidationError, match="no surface area"):
        gaussians_from_mesh(np.zeros((3, 3)), [[0, 1, 2]], [[0.5, 0.5, 0.5]])


def test_pool_build_over_asset_ids_and_kinds(tmp_path):
    import subprocess
    import sys

    from omniscs.agents.pool import Pool

    cli = [sys.executable, "-c", "from omniscs.cli import main; main()", "pool", "build"]
    proc = subprocess.run(cli + ["--assets", "sedan-0001,traffic_cone", "--out", str(tmp_path / "pool"),
                                 "--gaussians", "2000", "--refine-steps", "5"], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    pool = Pool(tmp_path / "pool")
    table = pool.table()
    assert len(table) == 13 and set(table.category) == {"car", "traffic_cone"}
    assert set(table.provenance) == {"mesh"} and table.quality.notna().all()
    assert pool.keyframes(table.model_id[0]).shape == (30, 96, 96, 4)
    bad = subprocess.run(cli + ["--assets", "spaceship-0001", "--out", str(tmp_path / "p2")], capture_output=True,
                         text=True, timeout=120)
    assert bad.returncode == 2 and bad.stderr.strip().count("\n") == 0
