"""The agents commands: pool match, fit --pool (the completed graph in --out), render --pool with pool model ids."""
import json

import pytest
from typer.testing import CliRunner

from omniscs.agents.pool import Pool
from omniscs.cli import app
from tests.nsg_fixtures import nsg_world, write_nsg_scene

#: A pool build and a 360-degree fit, about 45 s: in `make test-slow` (make test's five minutes).
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return write_nsg_scene(tmp_path_factory.mktemp("agents-cli") / "scene", nsg_world(n_frames=5))


@pytest.fixture(scope="module")
def pool(tmp_path_factory):
    from omniscs.agents.mesh import model_from_mesh
    from omniscs.world.assets import build_asset

    p = Pool(tmp_path_factory.mktemp("pool") / "pool")
    for aid in ("sedan-0047", "van-0025"):
        a = build_asset(aid)
        params, _ = model_from_mesh(a.surface.vertices, a.surface.faces, a.surface.face_colour, 1000, 0)
        p.add(params, a.category, "mesh", aid)
    return p


def test_pool_match_prints_one_model_per_vehicle_track(store, pool):
    result = CliRunner().invoke(app, ["pool", "match", str(store), "--pool", str(pool.root)])
    assert result.exit_code == 0, result.output
    got = json.loads(result.stdout[result.stdout.index("{"):])
    assert set(got) == {"1", "2"}
    assert {g["model_id"] for g in got.values()} == set(pool.table().model_id)  # one model each (Hungarian)
    bad = CliRunner().invoke(app, ["pool", "match", str(store), "--pool", str(pool.root), "--tracks", "9"])
    assert bad.exit_code != 0 and "no track(s) [9]" in str(bad.exception)


def test_fit_with_a_pool_writes_the_completed_graph_and_render_takes_pool_ids(store, pool, tmp_path):
    out = tmp_path / "graph"
    turn = '[{"op": "rotate", "track_id": 1, "yaw_deg": 180}]'
    result = CliRunner().invoke(app, ["fit", str(store), "--out", str(out), "--preset", "fast", "--iterations", "20",
                                      "--edit", turn, "--pool", str(pool.root), "--workspace", str(tmp_path / "ws")])
    assert result.exit_code == 0, result.output
    assert "track 1: pool -> pm-" in result.output and (out / "decisions.json").is_file()
    model_id = pool.table().model_id.iloc[0]
    png = tmp_path / "swap.png"
    result = CliRunner().invoke(app, ["render", str(out), "--out", str(png), "--pool", str(pool.root), "--edit",
                                      json.dumps([{"op": "replace_model", "track_id": 2, "asset_id": model_id}])])
    assert result.exit_code == 0, result.output
    assert png.is_file()
    missing = CliRunner().invoke(app, ["fit", str(store), "--out", str(tmp_path / "g2"), "--edit", turn,
                                       "--pool", str(tmp_path / "nowhere"), "--workspace", str(tmp_path / "ws")])
    assert missing.exit_code != 0 and "not a pool folder" in str(missing.exception)
    assert not (tmp_path / "g2").exists()
