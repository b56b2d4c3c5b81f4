"""Catalog: declared schemas are enforced on write, files are per task, DuckDB views query them."""
import re
from pathlib import Path

import pytest

from omniscs import catalog
from omniscs.errors import OmniscsError
from omniscs.scene import load_scene
from omniscs.scene.summary import MOVING_PATH_LENGTH_M, agent_rows, frame_rows, scene_row


def _frame(i=0, **kw):
    row = dict(scene_id="s", frame_idx=i, timestamp_us=i * 100_000, ego_x=0.0, ego_y=0.0, ego_z=0.0, ego_yaw=0.0,
               ego_speed_mps=0.0, n_boxes=0, n_visible_agents=None)
    row.update(kw)
    return row


def _run(root, run_id, status="completed", finished_at_us=1):
    """The run's ``runs`` row: the run ended."""
    catalog.write_rows(root, "runs", run_id, [dict(flow="test", status=status, started_at_us=0,
                                                   finished_at_us=finished_at_us, n_scenes=1, config_json="{}",
                                                   omniscs_version="test")], writer="run")


def test_each_write_is_a_new_file_in_its_run_partition(tmp_path):
    p1 = catalog.write_rows(tmp_path, "frames", "run-a", [_frame(0)], writer="t1")
    p2 = catalog.write_rows(tmp_path, "frames", "run-a", [_frame(1)], writer="t1")
    p3 = catalog.write_rows(tmp_path, "frames", "run-b", [_frame(0)], writer="t2")
    assert len({p1, p2, p3}) == 3 and p1.parent == p2.parent != p3.parent
    assert p1.parent.name == "run_id=run-a"
    assert re.fullmatch(r"t1-[0-9]{16}-[0-9a-f]{12}\.parquet", p1.name)  # writer, write time (us), unique part
    rows = catalog.query(tmp_path, "SELECT run_id, count(*) n FROM frames_raw GROUP BY 1 ORDER BY 1").to_pylist()
    assert rows == [{"run_id": "run-a", "n": 2}, {"run_id": "run-b", "n": 1}]


@pytest.mark.parametrize("row, message", [
    (_frame(extra_field=1), "undeclared field"),
    ({k: v for k, v in _frame().items() if k != "timestamp_us"}, "lacks required field"),
    (_frame(frame_idx="three"), "does not fit the schema"),
])
def test_rows_that_break_the_schema_are_refused_and_nothing_is_written(tmp_path, row, message):
    with pytest.raises(OmniscsError, match=message):
        catalog.write_rows(tmp_path, "frames", "r", [row])
    assert not any(tmp_path.rglob("*.parquet"))


def test_unsafe_run_id_and_unknown_table_are_refused(tmp_path):
    with pytest.raises(OmniscsError, match="run id"):
        catalog.write_rows(tmp_path, "frames", "../escape", [_frame()])
    with pytest.raises(OmniscsError, match="unknown catalog table"):
        catalog.write_rows(tmp_path, "nope", "r", [{}])


def test_empty_catalog_has_every_view_with_its_columns(tmp_path):
    for table, schema in catalog.SCHEMAS.items():
        for view, extra in [(table, []), (f"{table}_by_run", []), (f"{table}_raw", ["file"])]:
            result = catalog.query(tmp_path, f"SELECT * FROM {view}")
            assert result.num_rows == 0
            assert result.column_names == ["run_id", *schema.names, *extra]
            assert result.schema.field("run_id").type == "string"
            for field in schema:  # typed as declared, not as whatever a file happened to hold
                assert result.schema.field(field.name).type == field.type, (view, field.name)


def test_bad_sql_is_a_one_line_domain_error(tmp_path):
    with pytest.raises(OmniscsError, match="catalog query failed"):
        catalog.query(tmp_path, "SELEC nonsense")


def test_summaries_of_a_scene_fit_their_schemas_and_measure_motion(tiny_scene, tmp_path):
    scene = load_scene(tiny_scene)
    agents = agent_rows(scene)
    by_id = {a["track_id"]: a for a in agents}
    # track 0 stands still; track 1 moves 0.5 m per frame over 5 frames = 2 m
    assert not by_id[0]["moving"] and by_id[0]["path_length_m"] == 0.0
    assert by_id[1]["moving"] and by_id[1]["path_length_m"] == pytest.approx(2.0)
    assert 2.0 > MOVING_PATH_LENGTH_M
    assert by_id[1]["max_speed_mps"] == pytest.approx(5.0)
    frames = frame_rows(scene)
    assert frames[2]["ego_speed_mps"] == pytest.approx(10.0) and frames[0]["n_boxes"] == 2
    root = tmp_path / "cat"
    _run(root, "r1")
    catalog.write_rows(root, "agents", "r1", agents)
    catalog.write_rows(root, "frames", "r1", frames)
    catalog.write_rows(root, "scenes", "r1", [scene_row(scene, agents, reused=False, ingest_seconds=0.1)])
    got = catalog.query(root, "SELECT s.scene_id, s.n_moving, count(a.track_id) n FROM scenes s "
                              "JOIN agents a USING (run_id, scene_id) GROUP BY ALL").to_pylist()
    assert got == [{"scene_id": "tiny", "n_moving": 1, "n": 2}]


def test_checked_in_views_sql_matches_the_declared_schemas():
    text = (Path(__file__).parents[2] / "catalogs" / "views.sql").read_text()
    assert text == catalog.views_sql()
