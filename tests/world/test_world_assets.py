"""Asset library: stable ids, distinct parametric meshes that fit their boxes, clear errors."""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from omniscs.errors import OmniscsError
from omniscs.taxonomy import CATEGORIES, SEMANTIC_IDS, VEHICLE_CATEGORIES
from omniscs.world import asset_category, build_asset, list_asset_ids
from omniscs.world.assets import ASSET_KINDS, Material, asset_params


def _mesh_digest(asset_id: str) -> str:
    s = build_asset(asset_id).surface
    h = hashlib.sha256()
    for arr in (np.round(s.vertices, 6), s.faces, np.round(s.face_colour, 5), s.face_material):
        h.update(np.ascontiguousarray(arr).tobytes())
    return h.hexdigest()


def test_library_has_at_least_200_unique_ids_covering_every_required_kind():
    ids = list_asset_ids()
    assert len(ids) >= 200
    assert len(set(ids)) == len(ids)
    kinds = {i.rsplit("-", 1)[0] for i in ids}
    assert {"sedan", "suv", "van", "pickup", "box_truck", "bus", "trailer", "traffic_cone", "barrier",
            "debris"} <= kinds
    assert {"excavator", "wheel_loader"} & kinds


def test_every_asset_has_distinct_parameters_and_a_distinct_mesh():
    ids = list_asset_ids()
    params = {json.dumps(asset_params(i), sort_keys=True, default=lambda a: np.round(a, 6).tolist()) for i in ids}
    assert len(params) == len(ids)
    assert len({_mesh_digest(i) for i in ids}) == len(ids)


@pytest.mark.slow
def test_same_id_builds_the_identical_mesh_in_a_fresh_process():
    ids = ["sedan-0007", "bus-0003", "debris-0011", "excavator-0002"]
    code = ("import sys; sys.path.insert(0, 'tests/world'); from test_world_assets import _mesh_digest; "
            f"print(','.join(_mesh_digest(i) for i in {ids!r}))")
    env = dict(os.environ, PYTHONHASHSEED="12345")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True,
                         cwd=os.path.dirname(os.path.dirname(os.path.dirname(__file__))))
    assert out.stdout.strip().split(",") == [_mesh_digest(i) for i in ids]


@pytest.mark.parametrize("kind", sorted(ASSET_KINDS))
def test_mesh_fills_its_box_centred_on_the_origin(kind):
    for aid in list_asset_ids(kind)[:4]:
        a = build_asset(aid)
        lo, hi = a.surface.vertices.min(0), a.surface.vertices.max(0)
        assert np.all(a.size > 0)
        np.testing.assert_allclose(lo, -a.size / 2, atol=1e-9)
        np.testing.assert_allclose(hi, a.size / 2, atol=1e-9)
        assert len(a.surface.face_material) == len(a.surface.faces) == len(a.mesh.faces)


def test_vehicles_are_longer_than_wide_and_face_plus_x():
    for aid in list_asset_ids("sedan")[:10] + list_asset_ids("bus")[:3]:
        a = build_asset(aid)
        assert a.size[0] > a.size[1]
        # Headlights sit at the front (+x), tail lights at the back.
        s = a.surface
        centroids = s.vertices[s.faces].mean(1)
        assert centroids[s.face_material == Material.HEADLIGHT, 0].min() > 0
        assert centroids[s.face_material == Material.TAILLIGHT, 0].max() < 0


def test_categories_and_semantics_follow_the_taxonomy():
    for aid in list_asset_ids():
        cat = asset_category(aid)
        assert cat in CATEGORIES
        sem = build_asset(aid).surface.face_semantic
        expected = SEMANTIC_IDS["vehicle"] if cat in VEHICLE_CATEGORIES else SEMANTIC_IDS["obstacle"]
        assert np.all(sem == expected)


@pytest.mark.parametrize("bad", ["spaceship-0001", "sedan-9999", "sedan-7", "sedan", "", 42, None])
def test_bad_asset_ids_raise_a_domain_error(bad):
    with pytest.raises(OmniscsError):
        build_asset(bad)
    with pytest.raises(OmniscsError):
        asset_category(bad)


def test_unknown_kind_listing_raises():
    with pytest.raises(OmniscsError):
        list_asset_ids("hovercraft")


def test_pool_split_is_disjoint_from_the_world_split_and_holds_over_800_vehicles():
    from omniscs.taxonomy import VEHICLE_CATEGORIES
    from omniscs.world.assets import asset_category, asset_split

    world, pool, every = list_asset_ids(), list_asset_ids(split="pool"), list_asset_ids(split="all")
    assert not set(world) & set(pool)
    assert sorted(every) == sorted(world + pool)
    vehicles = [a for a in every if asset_category(a) in VEHICLE_CATEGORIES]
    assert len(vehicles) >= 1000
    assert {asset_split(a) for a in world} == {"world"} and {asset_split(a) for a in pool} == {"pool"}
    # pool instances are new, distinct parameter draws of the same families
    sample = pool[::40]
    params = {json.dumps(asset_params(i), sort_keys=True, default=lambda a: np.round(a, 6).tolist())
              for i in sample + world[::10]}
    assert len(params) == len(sample) + len(world[::10])
    with pytest.raises(OmniscsError, match="out of range"):
        build_asset("sedan-9999")
    with pytest.raises(OmniscsError, match="unknown asset split"):
        list_asset_ids(split="train")


def test_worlds_place_only_world_split_assets():
    from omniscs.world import generate_world
    from omniscs.world.assets import asset_split

    for template, seed in (("straight", 3), ("t_junction", 8)):
        world = generate_world(template, seed)
        assert {asset_split(a.asset_id) for a in world.agents} == {"world"}
