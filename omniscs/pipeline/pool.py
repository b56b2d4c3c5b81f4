"""The pool stage (Prefect-free): one asset of the world's library made into a pool model and added, with its
``pool`` catalog row."""
from __future__ import annotations

import time
from pathlib import Path

from omniscs.agents.mesh import model_from_mesh
from omniscs.agents.pool import Pool, model_id_of
from omniscs.errors import ValidationError
from omniscs.pipeline.records import StageRecord
from omniscs.taxonomy import VEHICLE_CATEGORIES
from omniscs.world.assets import ASSET_KINDS, SPLITS, asset_category, build_asset, list_asset_ids
from omniscs.world.render import F0, SHININESS


def asset_ids(items: list[str]) -> list[str]:
    """Asset ids of ``items``: ids of the asset library, kinds (``sedan``: the kind's world split), a split's
    vehicles (``pool``, ``world``) or a split of one kind (``pool:sedan``)."""
    ids: list[str] = []
    for item in (i.strip() for i in items):
        split, _, kind = item.rpartition(":")
        if not item:
            continue
        if item in SPLITS:
            ids += [a for a in list_asset_ids(split=item) if asset_category(a) in VEHICLE_CATEGORIES]
        elif kind in ASSET_KINDS:
            if split and split not in SPLITS:
                raise ValidationError(f"unknown asset split {split!r} in {item!r}; use one of {list(SPLITS)}")
            ids += list_asset_ids(kind, split or "world")
        else:
            asset_category(item)  # a clear error for an unknown id
            ids.append(item)
    if not ids:
        raise ValidationError("give at least one asset id, kind or split (world, pool) of the asset library")
    return list(dict.fromkeys(ids))


def pool_asset_stage(asset_id: str, pool: str | Path, gaussians: int = 20_000, refine_steps: int = 100) -> StageRecord:
    """``asset_id`` (a mesh of the asset library) as a pool model of ``pool`` (added once: the same model again is
    the same entry, ``new`` false). A pool keeps the model it holds of an asset even when the mesh build has changed
    since (its ``model.json`` "build" says which made it; none: version 1), so the datasets made from a pool stay
    reproducible; build into a new pool to get the current build's models."""
    started = time.perf_counter()
    p = Pool(pool)
    table = p.table()
    same = table[(table.source == asset_id) & (table.provenance == "mesh") & (table.n_gaussians == gaussians)] \
        if len(table) else table
    if len(same):  # built before with these settings (the build is deterministic): neither mesh nor model again
        model_id, existed = str(same.model_id.iloc[0]), True
    else:
        asset = build_asset(asset_id)
        s = asset.surface
        # the faces' optics as the world's renderer gives them to the asset's materials (paint, glass, chrome, ...)
        params, info = model_from_mesh(s.vertices, s.faces, s.face_colour, gaussians, refine_steps,
                                       face_specular=F0[s.face_material], face_shininess=SHININESS[s.face_material])
        material = info["material"]
        existed = model_id_of(params, asset.category, material) in set(table.model_id) if len(table) else False
        model_id = p.add(params, asset.category, "mesh", asset_id, quality=info["quality_psnr"], build=info["build"],
                         material=material)
    meta = p.get(model_id).meta
    length, width, height = meta["size"]
    row = {"pool_path": str(Path(pool).resolve()), "model_id": model_id, "category": meta["category"],
           "length": length, "width": width, "height": height, "n_gaussians": meta["n_gaussians"],
           "provenance": "mesh", "source": asset_id, "quality": meta["quality"], "new": not existed,
           "seconds": time.perf_counter() - started}
    return StageRecord("pool", asset_id, str(Path(pool) / "models" / model_id), reused=existed,
                       seconds=row["seconds"], rows={"pool": [row]}, info={"model_id": model_id})
