"""The model pool: content-addressed entries (the same model added twice is one entry), exact storage, a turned
splat file imported into its vehicle frame and exported again, two writers at once, clear errors; and rigid motion
of Gaussians with their view-dependent colours."""
from __future__ import annotations

import multiprocessing as mp

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial.transform import Rotation

from omniscs.agents.pool import Pool, calibrated, model_id_of
from omniscs.errors import OmniscsError, ValidationError
from omniscs.gaussians import params_from_values, rigidly_moved


def _model(seed: int = 0, n: int = 300, degree: int = 1):
    g = torch.Generator().manual_seed(seed)
    p = params_from_values(torch.randn(n, 3, generator=g) * torch.tensor([2.0, 0.9, 0.7]), torch.full((n, 3), 0.05),
                           torch.full((n,), 0.8), torch.rand(n, 3, generator=g), degree,
                           quats=torch.randn(n, 4, generator=g))
    return type(p)(p.means, p.quats, p.log_scales, p.opacity_logits, p.sh_dc,
                   0.2 * torch.randn(p.sh_rest.shape, generator=g))


def test_a_model_added_twice_is_one_entry_stored_exactly(tmp_path):
    pool = Pool(tmp_path / "pool")
    params = _model()
    a = pool.add(params, "car", "mesh", "sedan-0001", quality=31.5)
    b = pool.add(params, "car", "mesh", "sedan-0001", quality=31.5)
    assert a == b == model_id_of(params, "car") and a.startswith("pm-")
    assert pool.add(_model(1), "car", "mesh", "sedan-0002") != a
    table = pool.table()
    assert sorted(table.model_id) == sorted({a, model_id_of(_model(1), "car")}) and len(table) == 2
    got = pool.get(a)
    for name, t in params.as_dict().items():
        assert torch.equal(getattr(got.params, name), t), name
    assert got.meta["category"] == "car" and got.meta["quality"] == 31.5 and got.meta["sh_degree"] == 1
    assert table.set_index("model_id").loc[a, "length"] == pytest.approx(float(np.ptp(params.means[:, 0].numpy())))


def test_the_table_reads_rows_without_a_quality_as_missing_numbers(tmp_path):
    """A row written with no quality (an imported model) stores a null column; read with rows that have one, or
    alone, the quality is a float column with NaN, and the other columns keep their types."""
    pool = Pool(tmp_path / "pool")
    a = pool.add(_model(2), "car", "imported", "a.ply")
    alone = pool.table()
    assert alone.quality.dtype == np.float64 and np.isnan(alone.quality.iloc[0])
    b = pool.add(_model(3), "truck", "mesh", "box_truck-0001", quality=20.25)
    table = pool.table().set_index("model_id")
    assert np.isnan(table.loc[a, "quality"]) and table.loc[b, "quality"] == 20.25
    assert table.n_gaussians.dtype == np.int64 and table.loc[b, "category"] == "truck"


def test_rigid_motion_turns_positions_orientations_and_view_dependent_colour():
    from omniscs.render.sh import sh_basis

    params = _model(degree=3)
    R = Rotation.random(random_state=4).as_matrix()
    t = np.array([1.0, -2.0, 0.5])
    moved = rigidly_moved(params, R, t)
    np.testing.assert_allclose(moved.means.numpy(), params.means.numpy() @ R.T + t, atol=1e-5)
    d = torch.nn.functional.normalize(torch.randn(50, 3, dtype=torch.float64), dim=-1)
    new = torch.einsum("dk,nkc->ndc", sh_basis(3, d @ torch.as_tensor(R).T), moved.sh.double())  # seen from R d
    old = torch.einsum("dk,nkc->ndc", sh_basis(3, d), params.sh.double())                       # seen from d
    torch.testing.assert_close(new, old, atol=1e-5, rtol=1e-5)


def test_a_turned_splat_file_is_imported_in_its_vehicle_frame_and_exported_exactly(tmp_path):
    from omniscs.agents.ply import read_gaussian_ply, write_gaussian_ply
    from omniscs.world.assets import build_asset

    asset = build_asset("sedan-0003")
    pts, face = trimesh.sample.sample_surface(asset.mesh, 3000, seed=3)
    colours = np.clip(np.asarray(asset.surface.face_colour)[face] ** (1 / 2.2), 0, 1)  # roughly sRGB
    car = params_from_values(torch.as_tensor(pts, dtype=torch.float32), torch.full((len(pts), 3), 0.03),
                             torch.full((len(pts),), 0.9), torch.as_tensor(colours, dtype=torch.float32), 0)
    R = Rotation.random(random_state=9).as_matrix()
    turned = rigidly_moved(car, R, [3.0, -1.0, 7.0])  # as a generator might hand it over: any frame
    write_gaussian_ply(turned, tmp_path / "car.ply")
    pool = Pool(tmp_path / "pool")
    model_id = pool.import_ply(tmp_path / "car.ply", "car")
    got = pool.get(model_id)
    assert got.meta["provenance"] == "imported" and got.meta["calibration"]["heading_by"] in ("shape", "colour", "tie")
    err = np.linalg.norm(got.params.means.numpy() - pts, axis=1)
    assert np.percentile(err, 95) < 0.05, np.percentile(err, 95)  # back where the asset had them
    np.testing.assert_allclose(np.asarray(got.meta["size"]), asset.size, atol=0.08)
    pool.export_ply(model_id, tmp_path / "out.ply")
    back = read_gaussian_ply(tmp_path / "out.ply")
    assert all(torch.equal(getattr(back, k), v) for k, v in got.params.as_dict().items())


def _add_in_process(root: str, seeds: list[int]) -> list[str]:
    pool = Pool(root)
    return [pool.add(_model(s), "car", "mesh", f"seed-{s}") for s in seeds]


@pytest.mark.slow
def test_two_writers_at_once_lose_nothing_and_write_nothing_twice(tmp_path):
    root = str(tmp_path / "pool")
    with mp.get_context("spawn").Pool(2) as workers:
        a, b = workers.starmap(_add_in_process, [(root, [0, 1, 2, 3]), (root, [2, 3, 4, 5])])
    table = Pool(root).table()
    assert sorted(table.model_id) == sorted(set(a) | set(b)) and len(table) == 6
    for model_id in table.model_id:
        assert len(Pool(root).get(model_id).params) == 300
    assert not [p for p in (tmp_path / "pool" / "models").iterdir() if not p.name.startswith("pm-")]


def test_a_removed_model_leaves_the_table_and_its_files_and_can_be_added_again(tmp_path):
    pool = Pool(tmp_path / "pool")
    keep, gone = pool.add(_model(0), "car", "mesh", "sedan-0001"), pool.add(_model(1), "truck", "mesh", "box-0002")
    meta = pool.remove(gone)
    assert meta["model_id"] == gone and meta["category"] == "truck" and meta["source"] == "box-0002"
    assert list(pool.table().model_id) == [keep]
    assert sorted(p.name for p in (tmp_path / "pool" / "models").iterdir()) == [keep]  # no folder, temp or lock left
    assert sorted(p.name for p in (tmp_path / "pool" / "index").iterdir()) == [f"{keep}.parquet"]
    with pytest.raises(ValidationError, match="has no model"):
        pool.get(gone)
    with pytest.raises(ValidationError, match="has no model"):  # twice: a clear error, nothing else changes
        pool.remove(gone)
    with pytest.raises(OmniscsError, match="not a safe id"):
        pool.remove("../models")
    assert list(pool.table().model_id) == [keep] and len(pool.get(keep).params) == 300
    assert pool.add(_model(1), "truck", "mesh", "box-0002") == gone  # the same content, the same id, back again
    assert sorted(pool.table().model_id) == sorted([keep, gone]) and len(pool.get(gone).params) == 300


@pytest.mark.slow
def test_removing_while_another_process_adds_the_same_model_leaves_a_whole_entry_or_none(tmp_path):
    """Adding and removing the same model at once (one lock per model): whatever order they take, the pool ends
    either holding the model whole (row, parameters, keyframes) or not at all, never a row without its model."""
    root = str(tmp_path / "pool")
    model_id = Pool(root).add(_model(4), "car", "mesh", "x")
    with mp.get_context("spawn").Pool(2) as workers:
        added = workers.apply_async(_add_in_process, (root, [4, 4, 4]))
        removed = workers.apply_async(_remove_in_process, (root, model_id, 3))
        added.get(timeout=120), removed.get(timeout=120)
    pool = Pool(root)
    listed = list(pool.table().model_id)
    assert listed in ([], [model_id])
    if listed:
        assert len(pool.get(model_id).params) == 300 and pool.keyframes(model_id).shape[0] == 30
    else:
        assert not (tmp_path / "pool" / "models" / model_id).exists()
    assert not [p for p in (tmp_path / "pool" / "models").iterdir() if not p.name.startswith("pm-")]


def test_bad_models_and_ids_are_clear_errors(tmp_path):
    pool = Pool(tmp_path / "pool")
    with pytest.raises(ValidationError, match="unknown category"):
        pool.add(_model(), "spaceship", "mesh", "x")
    with pytest.raises(ValidationError, match="provenance"):
        pool.add(_model(), "car", "dream", "x")
    bad = _model()
    bad.means[0, 0] = float("nan")
    with pytest.raises(ValidationError, match="finite"):
        pool.add(bad, "car", "mesh", "x")
    with pytest.raises(ValidationError, match="at least one"):
        pool.add(_model().select(torch.zeros(300, dtype=torch.bool)), "car", "mesh", "x")
    with pytest.raises(ValidationError, match="has no model"):
        pool.get("pm-000000000000")
    model_id = pool.add(_model(), "car", "mesh", "x")
    (tmp_path / "pool" / "models" / model_id / "gaussians.safetensors").write_bytes(b"garbage")
    with pytest.raises(ValidationError, match="damaged"):
        pool.get(model_id)
    assert len(Pool(tmp_path / "empty").table()) == 0
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValidationError, match="is a file"):
        Pool(tmp_path / "file")
    with pytest.raises(ValidationError):
        calibrated(_model(n=5), "car")


@pytest.mark.slow
def test_the_pool_commands_import_list_and_export_with_the_id_alone_on_the_last_line(tmp_path):
    import json
    import subprocess
    import sys

    from omniscs.agents.ply import read_gaussian_ply, write_gaussian_ply

    write_gaussian_ply(_model(), tmp_path / "m.ply")
    cli = [sys.executable, "-c", "from omniscs.cli import main; main()", "pool"]
    run = lambda *a: subprocess.run(cli + list(a), capture_output=True, text=True, timeout=120)  # noqa: E731
    imported = run("import", str(tmp_path / "m.ply"), "--category", "car", "--pool", str(tmp_path / "pool"),
                   "--no-calibrate")
    assert imported.returncode == 0, imported.stderr
    model_id = imported.stdout.strip().splitlines()[-1]
    assert model_id == model_id_of(read_gaussian_ply(tmp_path / "m.ply"), "car")
    listed = run("list", str(tmp_path / "pool"), "--json")
    assert [json.loads(line)["model_id"] for line in listed.stdout.splitlines()] == [model_id]
    assert run("export", model_id, "--out", str(tmp_path / "out.ply"), "--pool", str(tmp_path / "pool")).returncode == 0
    assert torch.equal(read_gaussian_ply(tmp_path / "out.ply").means, read_gaussian_ply(tmp_path / "m.ply").means)
    removed = run("remove", model_id, "--pool", str(tmp_path / "pool"))
    assert removed.returncode == 0 and model_id in removed.stdout, removed.stderr
    assert run("list", str(tmp_path / "pool"), "--json").stdout.strip() == ""
    again = run("remove", model_id, "--pool", str(tmp_path / "pool"))
    assert again.returncode == 2 and "has no model" in again.stderr
    bad = run("import", str(tmp_path / "m.ply"), "--category", "ufo", "--pool", str(tmp_path / "pool"))
    assert bad.returncode == 2 and "unknown category" in bad.stderr and bad.stderr.strip().count("\n") == 0


@pytest.mark.parametrize("suffix", [".glb", ".obj", ".ply"])
@pytest.mark.slow
def test_a_user_mesh_is_made_into_a_calibrated_pool_model(tmp_path, suffix):
    """A library vehicle written as a coloured mesh, turned and moved at random, comes back box-centred, +x
    heading, at its size; a file with no triangles is one clear error."""
    from omniscs.geometry import make_transform, rotmat_from_euler, transform_points
    from omniscs.world.assets import build_asset

    a = build_asset("suv-0036")
    T = make_transform(rotmat_from_euler(yaw=1.1), np.array([3.0, -2.0, 0.5]))
    c = np.clip(a.surface.face_colour, 0, 1)
    srgb = np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)
    mesh = trimesh.Trimesh(transform_points(T, a.surface.vertices), a.surface.faces, process=False,
                           face_colors=(np.hstack([srgb, np.ones((len(c), 1))]) * 255).astype(np.uint8))
    path = tmp_path / f"suv{suffix}"
    mesh.export(path)
    pool = Pool(tmp_path / "pool")
    model_id = pool.import_file(path, "car")
    meta = pool.get(model_id).meta
    assert meta["provenance"] == "imported" and meta["source"] == path.name and meta["n_gaussians"] == 20_000
    assert np.allclose(meta["size"], a.size, rtol=0.08)  # heading and axes recovered: length along +x
    assert meta["calibration"]["heading_by"]
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing\n")
    with pytest.raises(ValidationError):
        pool.import_file(empty, "car")


def _remove_in_process(root: str, model_id: str, times: int) -> int:
    removed = 0
    for _ in range(times):
        try:
            Pool(root).remove(model_id)
            removed += 1
        except ValidationError:  # already gone: the other process has not put it back yet
            pass
    return removed


def test_a_models_material_is_stored_with_it_and_part_of_its_id(tmp_path):
    from safetensors.torch import save_file

    from omniscs.agents.material import GaussianMaterial
    from omniscs.agents.pool import MATERIAL, MODELS

    pool = Pool(tmp_path / "pool")
    params = _model(n=50)
    g = torch.Generator().manual_seed(3)
    material = GaussianMaterial(torch.rand(50, 3, generator=g), torch.rand(50, generator=g) * 0.1,
                                1.0 + 300.0 * torch.rand(50, generator=g))
    with_m = pool.add(params, "car", "mesh", "sedan-0001", material=material)
    without = pool.add(params, "car", "mesh", "sedan-0001")
    assert with_m != without and with_m == model_id_of(params, "car", material)
    assert without == model_id_of(params, "car")
    got = pool.get(with_m).material
    assert all(torch.equal(getattr(got, k), getattr(material, k)) for k in ("albedo", "specular", "shininess"))
    assert pool.get(without).material is None
    with pytest.raises(ValidationError, match="material is for 10"):
        pool.add(params, "car", "mesh", "x", material=material.select(torch.arange(10)))
    with pytest.raises(ValidationError, match="albedo"):
        GaussianMaterial(torch.full((2, 3), 1.5), torch.zeros(2), torch.ones(2))
    with pytest.raises(ValidationError, match="NaN"):
        GaussianMaterial(torch.zeros(2, 3), torch.tensor([0.0, float("nan")]), torch.ones(2))
    # a material file for another number of Gaussians: the model reads as damaged, not half
    save_file(material.select(torch.arange(5)).as_dict(), str(pool.root / MODELS / with_m / MATERIAL))
    with pytest.raises(ValidationError, match="damaged"):
        pool.get(with_m)


@pytest.mark.parametrize("content", ["junk", "truncated", "foreign"])
def test_a_junk_truncated_or_foreign_index_file_is_one_error_naming_it(tmp_path, content):
    import pyarrow as pa
    import pyarrow.parquet as pq

    pool = Pool(tmp_path / "pool")
    a = pool.add(_model(2), "car", "imported", "a.ply")
    good = tmp_path / "pool" / "index" / f"{a}.parquet"
    bad = good.parent / "pm-000000000000.parquet"
    if content == "junk":
        bad.write_text("model_id,category\npm-1,car\n")
    elif content == "truncated":
        bad.write_bytes(good.read_bytes()[:100])
    else:
        pq.write_table(pa.table({"model_id": ["pm-000000000000"], "owner": ["someone else"]}), bad)
    with pytest.raises(OmniscsError) as info:
        pool.table()
    assert "\n" not in str(info.value) and str(bad) in str(info.value) and "remove that file" in str(info.value)
    bad.unlink()
    assert pool.table().model_id.tolist() == [a]


def test_a_model_of_huge_gaussians_or_a_huge_extent_is_refused(tmp_path):
    from omniscs.agents.pool import MAX_GAUSSIAN_SIZE_M
    from omniscs.errors import ValidationError

    pool = Pool(tmp_path / "pool")
    p = _model()
    huge = type(p)(p.means, p.quats, torch.full_like(p.log_scales, 80.0), p.opacity_logits, p.sh_dc, p.sh_rest)
    with pytest.raises(ValidationError, match="e\\^80"):
        pool.add(huge, "car", "imported", "x.ply")
    wide = type(p)(p.means * 100.0, p.quats, p.log_scales, p.opacity_logits, p.sh_dc, p.sh_rest)
    with pytest.raises(ValidationError, match="span at most"):
        pool.add(wide, "car", "imported", "x.ply")
    edge = type(p)(p.means, p.quats, torch.full_like(p.log_scales, float(np.log(MAX_GAUSSIAN_SIZE_M)) - 1e-3),
                   p.opacity_logits, p.sh_dc, p.sh_rest)
    assert pool.add(edge, "car", "imported", "x.ply").startswith("pm-")
    assert not (tmp_path / "pool" / "models").exists() or len(list((tmp_path / "pool" / "models").iterdir())) == 1
