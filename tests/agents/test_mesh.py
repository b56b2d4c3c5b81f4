"""Pool models from meshes: flat Gaussians on the surface that look like the mesh from every side (better after
refinement, on views they were not refined on), keyframes all around, clear errors for bad meshes, and the
``pool build`` command over the asset library."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from omniscs.agents.mesh import (MESH_BUILD_VERSION, gaussians_from_mesh, keyframes, model_from_mesh, orbit_cameras,
                                 raycast_views, view_psnr)
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


def _box(centre, size):
    m = trimesh.creation.box(extents=size)
    return np.asarray(m.vertices) + centre, np.asarray(m.faces)


def test_faces_buried_inside_other_parts_get_no_gaussians():
    # a body with a cabin sunk into it (the asset library builds vehicles so): the body's top under the cabin and
    # the cabin's lower part inside the body are seen from nowhere outside
    bv, bf = _box(np.zeros(3), [4.0, 2.0, 1.0])
    cv, cf = _box(np.array([0.0, 0.0, 0.6]), [2.0, 1.6, 1.0])
    v = np.concatenate([bv, cv])
    f = np.concatenate([bf, cf + len(bv)])
    colours = np.concatenate([np.full((len(bf), 3), 0.8), np.full((len(cf), 3), 0.1)])
    g = gaussians_from_mesh(v, f, colours, n=4000)
    m = g.means.numpy()
    inside_body = np.all(np.abs(m) < [2.0 - 1e-3, 1.0 - 1e-3, 0.5 - 1e-3], 1)
    inside_cabin = np.all(np.abs(m - [0.0, 0.0, 0.6]) < [1.0 - 1e-3, 0.8 - 1e-3, 0.5 - 1e-3], 1)
    assert len(g) == 4000 and not inside_body.any() and not inside_cabin.any()
    # the whole-surface sampling this replaced put about a tenth of its points there
    raw, _ = trimesh.sample.sample_surface(trimesh.Trimesh(v, f, process=False), 4000, seed=0)
    buried = np.all(np.abs(raw) < [2.0 - 1e-3, 1.0 - 1e-3, 0.5 - 1e-3], 1) | \
        np.all(np.abs(raw - [0.0, 0.0, 0.6]) < [1.0 - 1e-3, 0.8 - 1e-3, 0.5 - 1e-3], 1)
    assert buried.mean() > 0.05
    # a closed box alone loses nothing
    assert len(gaussians_from_mesh(bv, bf, np.full((len(bf), 3), 0.5), n=500)) == 500


def test_the_model_looks_like_the_mesh_from_views_it_was_not_refined_on(sedan):
    s = sedan.surface
    params, info = model_from_mesh(s.vertices, s.faces, s.face_colour, n=8000, refine_steps=40)
    held = orbit_cameras(sedan.size, 8, elevation_deg=45.0)
    rgb, alpha = raycast_views(s.vertices, s.faces, s.face_colour, held)
    raw = gaussians_from_mesh(s.vertices, s.faces, s.face_colour, n=8000)
    assert view_psnr(params, rgb, alpha, held) > view_psnr(raw, rgb, alpha, held) > 15.0
    assert info["quality_psnr"] > 15.0 and info["seconds"] < 30.0
    assert info["build"]["version"] == MESH_BUILD_VERSION and info["build"]["gaussians"] == 8000
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


@pytest.mark.slow
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
    build = pool.get(table.model_id[0]).meta["build"]  # which build made it, kept with the model
    assert build["version"] == MESH_BUILD_VERSION and build["gaussians"] == 2000 and build["refine_steps"] == 5
    # the library's faces' optics come with the model: a sedan's glass and paint mirror, its tyres do not
    car = pool.get(table.set_index("source").loc["sedan-0001", "model_id"]).material
    assert len(car) == 2000 and {0.0, 0.05, 0.09} <= set(np.round(car.specular.double().numpy(), 4).tolist())
    bad = subprocess.run(cli + ["--assets", "spaceship-0001", "--out", str(tmp_path / "p2")], capture_output=True,
                         text=True, timeout=120)
    assert bad.returncode == 2 and bad.stderr.strip().count("\n") == 0


def test_each_gaussian_keeps_its_faces_material():
    """Two boxes side by side, a matte red one and a shiny blue one: every Gaussian on the red box is matte and red,
    every one on the blue box shiny and blue; bad per-face arrays are clear errors."""
    va, fa = _box([-1.0, 0.0, 0.0], [1.0, 1.0, 1.0])
    vb, fb = _box([1.0, 0.0, 0.0], [1.0, 1.0, 1.0])
    v, f = np.concatenate([va, vb]), np.concatenate([fa, fb + len(va)])
    colours = np.array([[0.8, 0.1, 0.1]] * len(fa) + [[0.1, 0.1, 0.8]] * len(fb))
    spec = np.array([0.0] * len(fa) + [0.09] * len(fb))
    shin = np.array([1.0] * len(fa) + [400.0] * len(fb))
    params, info = model_from_mesh(v, f, colours, 1500, 0, face_specular=spec, face_shininess=shin)
    m, x = info["material"], params.means[:, 0].numpy()
    assert len(m) == len(params) == 1500
    red, blue = x < -0.01, x > 0.01
    assert red.any() and blue.any() and (red | blue).all()
    assert np.allclose(m.albedo.numpy()[red], [0.8, 0.1, 0.1]) and np.allclose(m.albedo.numpy()[blue], [0.1, 0.1, 0.8])
    assert (m.specular.numpy()[red] == 0).all() and np.allclose(m.specular.numpy()[blue], 0.09)
    assert np.allclose(m.shininess.numpy()[blue], 400.0)
    plain = model_from_mesh(v, f, colours, 500, 0)[1]["material"]  # no optics given: matte
    assert float(plain.specular.max()) == 0.0
    with pytest.raises(ValidationError, match="face_specular"):
        model_from_mesh(v, f, colours, 500, 0, face_specular=spec[:-1])
    with pytest.raises(ValidationError, match="face_shininess"):
        model_from_mesh(v, f, colours, 500, 0, face_shininess=np.full(len(f), np.nan))
