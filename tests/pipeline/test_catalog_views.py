"""Catalog views and queries: a query reads the catalog and nothing else, writes nothing; the default views show
each logical row once (ended runs only, a completed run first, then the run that finished last), ``_by_run`` once
per run, ``_raw`` every row of every file."""
import itertools
import subprocess
import sys
import types
from pathlib import Path

import duckdb
import pyarrow as pa
import pytest
from typer.testing import CliRunner

from omniscs import catalog
from omniscs.cli import app
from omniscs.errors import OmniscsError

runner = CliRunner()
DATA_TABLES = [t for t in catalog.SCHEMAS if t != "runs"]


@pytest.fixture
def clock(monkeypatch):
    """Write times 1 ms apart, so 'the newest file of a run' is known to the test."""
    ticks = itertools.count(1_700_000_000_000_000_000, 1_000_000)
    monkeypatch.setattr(catalog, "time", types.SimpleNamespace(time_ns=lambda: next(ticks)))


def _run(root, run_id, status="completed", finished_at_us=1):
    catalog.write_rows(root, "runs", run_id, [dict(flow="test", status=status, started_at_us=0,
                                                   finished_at_us=finished_at_us, n_scenes=1, config_json="{}",
                                                   omniscs_version="test")], writer="run")


def _row(table, **values):
    """A valid row of ``table``: every required field filled with a plain value, then ``values``."""
    fill = {pa.string(): "x", pa.int64(): 0, pa.int32(): 0, pa.float64(): 0.0, pa.bool_(): False}
    row = {f.name: ([] if pa.types.is_list(f.type) else fill[f.type]) for f in catalog.SCHEMAS[table]
           if not f.nullable}
    row.update(values)
    return row


def _agent(scene, track, length):
    return _row("agents", scene_id=scene, track_id=track, category="car", length=length)


def _files(path: Path) -> dict[str, int]:
    return {str(p.relative_to(path)): p.stat().st_size for p in path.rglob("*")}


# ----------------------------------------------------------------------------- read-only
@pytest.fixture
def workspace(tmp_path, clock):
    """A workspace with one ended run, a file beside the catalog that queries must not read, and an empty
    folder that queries must not write into."""
    ws = tmp_path / "ws"
    root = catalog.catalog_root(ws)
    _run(root, "r1")
    catalog.write_rows(root, "agents", "r1", [_agent("s1", 0, 4.0)], writer="scene-s1")
    (ws / "secret.txt").write_text("TOP-SECRET-BESIDE-THE-CATALOG\n")
    (tmp_path / "out").mkdir()
    return ws


def _forbidden(ws: Path) -> list[str]:
    root = catalog.catalog_root(ws)
    out = ws.parent / "out"
    return [
        f"COPY (SELECT 1) TO '{out}/x.csv'",
        f"COPY agents TO '{root}/agents/run_id=r1/x.parquet'",       # even inside the catalog root
        f"COPY (SELECT 1) TO '{root}/x.csv'",
        f"EXPORT DATABASE '{out}/export'",
        f"ATTACH '{out}/x.db'",
        f"ATTACH '{out}/x.db' AS x; CREATE TABLE x.t AS SELECT 1",
        "SELECT * FROM read_csv('/etc/passwd')",
        "SELECT * FROM read_csv('/etc/passwd', sep = ':', header = false)",
        "SELECT * FROM read_text('/etc/passwd')",
        "SELECT * FROM read_blob('/etc/passwd')",
        "SELECT * FROM '/etc/passwd'",
        "SELECT * FROM glob('/etc/*')",
        "SELECT * FROM glob('/root/*')",
        f"SELECT * FROM read_text('{ws}/secret.txt')",
        f"SELECT * FROM read_text('{root}/../secret.txt')",
        f"SELECT * FROM glob('{root}/../*')",
        "WITH p AS (SELECT * FROM read_text('/etc/passwd')) SELECT * FROM agents, p",
        "SELECT * FROM agents UNION ALL BY NAME SELECT * FROM read_csv('/etc/passwd')",
        "SELECT * FROM read_parquet('https://example.com/x.parquet')",
        "SELECT getenv('HOME')",
        "INSTALL httpfs",
        "LOAD httpfs",
        "SET threads = 1",
        "SET enable_external_access = true",
        "RESET lock_configuration",
        "PRAGMA threads = 1",
        f"SET VARIABLE {catalog.ROOT_VARIABLE} = '/etc'",
        "CREATE TABLE t AS SELECT 1",
        "CREATE OR REPLACE VIEW agents AS SELECT 1",
        "INSERT INTO agents_raw SELECT * FROM agents_raw",
        "DROP VIEW agents",
        "CALL pragma_version()",
        "SELECT 1; SELECT 2",
        f"SELECT 1; COPY (SELECT 1) TO '{out}/x.csv'",
        f"EXPLAIN COPY (SELECT 1) TO '{out}/x.csv'",
        f"SELECT * FROM query('COPY (SELECT 1) TO ''{out}/x.csv''')",
        "PIVOT agents ON category",
    ]


def test_every_forbidden_query_is_refused_in_one_line_and_nothing_is_read_or_written(workspace):
    root = catalog.catalog_root(workspace)
    before = _files(workspace.parent)
    passwd = Path("/etc/passwd").read_text().splitlines()[0] if Path("/etc/passwd").exists() else "root:x:0:0"
    for sql in _forbidden(workspace):
        with pytest.raises(OmniscsError) as info:
            catalog.query(root, sql)
        message = str(info.value)
        assert "\n" not in message, sql
        assert message.startswith(("catalog queries are read-only", "catalog query failed")), (sql, message)
        assert passwd not in message and "TOP-SECRET" not in message, sql
        assert _files(workspace.parent) == before, sql  # nothing written, in the catalog or anywhere beside it


@pytest.mark.parametrize("sql, statement", [
    ("COPY (SELECT 1) TO 'x.csv'", "COPY"), ("ATTACH 'x.db'", "ATTACH"), ("INSTALL httpfs", "LOAD"),
    ("SET threads = 1", "SET"), ("CREATE TABLE t (a INT)", "CREATE"), ("INSERT INTO agents_raw SELECT 1", "INSERT"),
])
def test_a_statement_that_is_not_a_select_is_named_in_the_refusal(tmp_path, sql, statement):
    with pytest.raises(OmniscsError, match=f"^catalog queries are read-only: only SELECT .*not {statement}"):
        catalog.query(tmp_path, sql)


def test_reads_outside_the_catalog_root_are_refused_by_duckdb_itself(workspace):
    with pytest.raises(OmniscsError, match="^catalog queries are read-only: .*Permission Error"):
        catalog.query(catalog.catalog_root(workspace), "SELECT * FROM read_csv('/etc/passwd')")
    with pytest.raises(OmniscsError, match="^catalog queries are read-only: .*Permission Error"):
        catalog.query(catalog.catalog_root(workspace), f"SELECT * FROM read_text('{workspace}/secret.txt')")


def test_the_connection_is_locked_down(workspace):
    got = catalog.query(catalog.catalog_root(workspace), """
        SELECT current_setting('enable_external_access') AS external, current_setting('lock_configuration') AS locked,
               current_setting('python_enable_replacements') AS replacements,
               current_setting('autoload_known_extensions') AS autoload,
               current_setting('autoinstall_known_extensions') AS autoinstall""").to_pylist()
    assert got == [{"external": False, "locked": True, "replacements": False, "autoload": False,
                    "autoinstall": False}]


@pytest.mark.parametrize("sql", ["", "   \n\t ", "-- only a comment", ";", " ; ;"])
def test_an_empty_query_is_one_clear_line(tmp_path, sql):
    with pytest.raises(OmniscsError, match="catalog query (is empty|holds no statement)") as info:
        catalog.query(tmp_path, sql)
    assert "\n" not in str(info.value)


def test_selects_and_explain_of_a_select_still_work(workspace):
    root = catalog.catalog_root(workspace)
    assert catalog.query(root, "SELECT scene_id, track_id FROM agents").to_pylist() == [
        {"scene_id": "s1", "track_id": 0}]
    assert catalog.query(root, "WITH a AS (SELECT * FROM agents_by_run) SELECT count(*) AS n FROM a;").to_pylist() \
        == [{"n": 1}]
    assert catalog.query(root, "FROM agents_raw SELECT run_id").to_pylist() == [{"run_id": "r1"}]
    for sql in ["EXPLAIN SELECT * FROM agents", "explain analyze SELECT count(*) FROM agents", "DESCRIBE agents",
                "SUMMARIZE agents_raw", "SHOW TABLES"]:
        assert catalog.query(root, sql).num_rows > 0, sql
    names = {r["name"] for r in catalog.query(root, "SHOW TABLES").to_pylist()}
    assert names == set(catalog.view_names())


# ----------------------------------------------------------------------------- paths
@pytest.mark.parametrize("name", ["it's here", "it's [a] *here?", "x=y"])
def test_a_workspace_path_with_quotes_glob_characters_or_equals_signs_works(tmp_path, clock, name):
    root = catalog.catalog_root(tmp_path / name)
    _run(root, "r1")
    catalog.write_rows(root, "agents", "r1", [_agent("s1", 0, 4.0), _agent("s1", 1, 5.0)])
    got = catalog.query(root, "SELECT * FROM agents ORDER BY track_id").to_pylist()
    assert [(r["run_id"], r["track_id"], r["length"]) for r in got] == [("r1", 0, 4.0), ("r1", 1, 5.0)]
    assert set(got[0]) == {"run_id", *catalog.SCHEMAS["agents"].names}  # no column made up from the path
    result = runner.invoke(app, ["catalog", "query", "SELECT count(*) AS n FROM agents", "--json",
                                 "--workspace", str(tmp_path / name)])
    assert result.exit_code == 0, result.output
    assert '"n": 2' in result.output


def test_views_sql_makes_the_same_views_as_queries_see(tmp_path, clock):
    """The statements for the duckdb shell, run in a plain connection, give what ``query`` gives, view by view."""
    root = tmp_path / "it's [here]" / "catalog"
    _write_history(root)
    con = duckdb.connect()
    con.execute(catalog.views_sql(str(root)))
    for view in catalog.view_names():
        shell = con.sql(f"SELECT * FROM {view} ORDER BY ALL").to_arrow_table()
        ours = catalog.query(root, f"SELECT * FROM {view} ORDER BY ALL")
        assert shell.to_pylist() == ours.to_pylist(), view
        assert shell.column_names == ours.column_names, view


# ----------------------------------------------------------------------------- one logical row once
def _write_history(root):
    """Run A completed (finished at 100), B failed (200), C killed (no runs row), D completed (50), F cancelled
    (300); A wrote (s2, 0) twice, the second time with length 1.5."""
    _run(root, "A", "completed", 100)
    _run(root, "B", "failed", 200)
    _run(root, "D", "completed", 50)
    _run(root, "F", "cancelled", 300)
    catalog.write_rows(root, "agents", "A", [_agent("s1", 0, 1.0), _agent("s1", 1, 1.0), _agent("s2", 0, 1.0)])
    catalog.write_rows(root, "agents", "A", [_agent("s2", 0, 1.5)])  # the same scene given twice in one run
    catalog.write_rows(root, "agents", "B", [_agent("s1", 0, 2.0), _agent("s3", 0, 2.0)])
    catalog.write_rows(root, "agents", "C", [_agent("s1", 0, 3.0), _agent("s4", 0, 3.0)])
    catalog.write_rows(root, "agents", "D", [_agent("s1", 0, 4.0), _agent("s2", 0, 4.0)])
    catalog.write_rows(root, "agents", "F", [_agent("s3", 0, 6.0)])


def _triples(root, view):
    rows = catalog.query(root, f"SELECT run_id, scene_id, track_id, length FROM {view} ORDER BY ALL").to_pylist()
    return [(r["run_id"], r["scene_id"], r["track_id"], r["length"]) for r in rows]


def test_default_view_shows_each_key_once_from_the_winning_run(tmp_path, clock):
    _write_history(tmp_path)
    assert _triples(tmp_path, "agents") == [
        ("A", "s1", 0, 1.0),   # completed A beats failed B (finished later) and completed D (finished earlier)
        ("A", "s1", 1, 1.0),
        ("A", "s2", 0, 1.5),   # A's newest file
        ("F", "s3", 0, 6.0),   # no completed run has it: the run that finished last (cancelled F after failed B)
    ]                          # (s4, 0) only in the killed run C: not shown
    assert catalog.query(tmp_path, "SELECT count(*) AS n FROM agents").to_pylist() == [{"n": 4}]


def test_by_run_view_shows_each_key_once_per_ended_run(tmp_path, clock):
    _write_history(tmp_path)
    assert _triples(tmp_path, "agents_by_run") == [
        ("A", "s1", 0, 1.0), ("A", "s1", 1, 1.0), ("A", "s2", 0, 1.5),
        ("B", "s1", 0, 2.0), ("B", "s3", 0, 2.0),
        ("D", "s1", 0, 4.0), ("D", "s2", 0, 4.0),
        ("F", "s3", 0, 6.0),
    ]
    assert _triples(tmp_path, "agents_by_run WHERE run_id = 'C'") == []


def test_raw_view_shows_every_row_of_every_file(tmp_path, clock):
    _write_history(tmp_path)
    got = _triples(tmp_path, "agents_raw")
    assert len(got) == 11
    assert ("C", "s4", 0, 3.0) in got and ("A", "s2", 0, 1.0) in got and ("A", "s2", 0, 1.5) in got
    files = catalog.query(tmp_path, "SELECT DISTINCT file FROM agents_raw").column("file").to_pylist()
    assert len(files) == 6 and all(Path(f).is_file() and Path(f).parent.name.startswith("run_id=") for f in files)


def test_runs_shows_a_rerun_run_id_once_as_it_finished_last(tmp_path, clock):
    _run(tmp_path, "E", "failed", 300)
    _run(tmp_path, "E", "completed", 400)
    _run(tmp_path, "G", "completed", 10)
    got = catalog.query(tmp_path, "SELECT run_id, status, finished_at_us FROM runs ORDER BY 1").to_pylist()
    assert got == [{"run_id": "E", "status": "completed", "finished_at_us": 400},
                   {"run_id": "G", "status": "completed", "finished_at_us": 10}]
    assert catalog.query(tmp_path, "SELECT * FROM runs_by_run ORDER BY run_id").to_pylist() == \
        catalog.query(tmp_path, "SELECT * FROM runs ORDER BY run_id").to_pylist()
    assert catalog.query(tmp_path, "SELECT count(*) AS n FROM runs_raw").to_pylist() == [{"n": 3}]


def test_within_a_run_a_file_named_before_write_times_counts_as_the_oldest(tmp_path, clock):
    _run(tmp_path, "A")
    catalog.write_rows(tmp_path, "agents", "A", [_agent("s1", 0, 2.0)])
    old = catalog.write_rows(tmp_path, "agents", "A", [_agent("s1", 0, 1.0)])
    old.rename(old.parent / "scene-s1-0123456789ab.parquet")  # the layout before names carried the time
    assert _triples(tmp_path, "agents") == [("A", "s1", 0, 2.0)]
    assert len(_triples(tmp_path, "agents_raw")) == 2


@pytest.mark.parametrize("table", DATA_TABLES)
def test_every_data_table_is_deduplicated_by_its_declared_key(tmp_path, clock, table):
    schema, key = catalog.SCHEMAS[table], catalog.KEYS[table]
    lead = key[0]  # scene_id, or dataset_id for the dataset tables
    column = next(f for f in schema if f.name not in key and not f.nullable
                  and f.type in (pa.string(), pa.int64(), pa.float64()))

    def row(owner, mark):
        keys = {k: (owner if k == lead else "k" if schema.field(k).type == pa.string() else 7) for k in key}
        return _row(table, **keys, **{column.name: str(mark) if column.type == pa.string() else mark})

    _run(tmp_path, "old", "completed", 1)
    _run(tmp_path, "new", "completed", 2)
    catalog.write_rows(tmp_path, table, "old", [row("s1", 1), row("s2", 1)])
    catalog.write_rows(tmp_path, table, "new", [row("s1", 2)])
    catalog.write_rows(tmp_path, table, "new", [row("s1", 3)])  # the same key again, later, in the same run
    got = catalog.query(tmp_path, f'SELECT run_id, "{lead}" AS owner, "{column.name}" AS v FROM {table} ORDER BY 2')
    cast = str if column.type == pa.string() else type(got.column("v").to_pylist()[0])
    assert got.to_pylist() == [{"run_id": "new", "owner": "s1", "v": cast(3)},
                               {"run_id": "old", "owner": "s2", "v": cast(1)}]
    assert catalog.query(tmp_path, f"SELECT count(*) AS n FROM {table}_by_run").to_pylist() == [{"n": 3}]
    assert catalog.query(tmp_path, f"SELECT count(*) AS n FROM {table}_raw").to_pylist() == [{"n": 4}]


def test_keys_are_declared_for_every_table_and_are_required_columns():
    assert set(catalog.KEYS) == set(catalog.SCHEMAS)
    for table, key in catalog.KEYS.items():
        for column in key:
            if column != "run_id":
                assert not catalog.SCHEMAS[table].field(column).nullable, (table, column)


# ----------------------------------------------------------------------------- the CLI
@pytest.mark.parametrize("command", [["query", "SELECT 1"], ["views"]])
def test_cli_refuses_a_missing_workspace_and_creates_nothing(tmp_path, monkeypatch, command):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("OMNISCS_HOME", raising=False)
    for extra in ([], ["--workspace", str(tmp_path / "nowhere")]):
        result = runner.invoke(app, ["catalog", *command, *extra])
        assert isinstance(result.exception, OmniscsError), result.output
        assert "no workspace at" in str(result.exception)
    assert list(tmp_path.iterdir()) == []


def test_cli_views_prints_the_views_for_the_workspace(workspace):
    result = runner.invoke(app, ["catalog", "views", "--workspace", str(workspace)])
    assert result.exit_code == 0, result.output
    assert result.output == catalog.views_sql(str(catalog.catalog_root(workspace)))


def test_cli_refuses_a_write_with_exit_2_and_one_line(workspace):
    target = workspace.parent / "out" / "x.csv"
    result = runner.invoke(app, ["catalog", "query", f"COPY (SELECT 1) TO '{target}'", "--workspace",
                                 str(workspace)])
    assert isinstance(result.exception, OmniscsError)
    assert str(result.exception).startswith("catalog queries are read-only: only SELECT")
    proc = subprocess.run([sys.executable, "-c", "from omniscs.cli import main; main()", "catalog", "query",
                           "SELECT * FROM read_csv('/etc/passwd')", "--workspace", str(workspace)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and "catalog queries are read-only" in proc.stderr
    assert proc.stdout == "" and not target.exists()


@pytest.mark.parametrize("content", ["junk", "truncated", "foreign"])
def test_a_junk_truncated_or_foreign_file_in_a_table_is_one_error_naming_it_and_never_rows(tmp_path, clock, content):
    import pyarrow.parquet as pq

    root = tmp_path / "catalog"
    _run(root, "r1")
    good = catalog.write_rows(root, "scenes", "r1", [_row("scenes", scene_id="s1")])
    bad = good.parent / "zz-dropped-here.parquet"
    if content == "junk":
        bad.write_bytes(b"not a parquet file\n")
    elif content == "truncated":
        bad.write_bytes(good.read_bytes()[: good.stat().st_size - 9])
    else:  # a real Parquet file of someone else's table: its rows must not show as scenes
        pq.write_table(pa.table({"scene_id": ["intruder"], "password": ["hunter2"]}), bad)
    with pytest.raises(OmniscsError) as info:
        catalog.query(root, "SELECT scene_id FROM scenes_raw")
    message = str(info.value)
    assert "\n" not in message and str(bad) in message and "move that file out of the catalog folder" in message
    assert "hunter2" not in message
    bad.unlink()
    assert catalog.query(root, "SELECT scene_id FROM scenes_raw").column("scene_id").to_pylist() == ["s1"]


def test_the_cli_refuses_a_junk_catalog_file_with_exit_2_and_one_line(tmp_path):
    ws = tmp_path / "ws"
    _run(catalog.catalog_root(ws), "r1")
    junk = catalog.catalog_root(ws) / "runs" / "run_id=r1" / "junk.parquet"
    junk.write_bytes(b"PAR1" + b"\x00" * 40 + b"PAR1")
    proc = subprocess.run([sys.executable, "-c", "from omniscs.cli import main; main()", "catalog", "query",
                           "SELECT * FROM runs", "--workspace", str(ws)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and str(junk) in proc.stderr.replace("\n", "")
