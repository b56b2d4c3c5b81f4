"""One path policy, applied before any work: outputs that are symbolic links (dangling or not) or lie under a
dangling one, names the file system cannot hold and folders that cannot be written are one clear error; a
workspace that points nowhere is refused, not created elsewhere; folders of a workspace (catalog tables, pool
models) that are links out of it are refused, not followed."""
from __future__ import annotations

import os

import pytest
from typer.testing import CliRunner

from omniscs import catalog
from omniscs.agents.pool import Pool
from omniscs.cli import app
from omniscs.errors import OmniscsError
from omniscs.storage import atomic_directory, check_output, usable_workspace
from tests.agents.test_pool import _model
from tests.dataset_fixtures import synthetic_store

runner = CliRunner()


def _entries(folder):
    return sorted(p.name for p in folder.iterdir())


def test_an_output_that_is_a_symbolic_link_or_lies_under_a_dangling_one_is_refused(tmp_path):
    (tmp_path / "real").mkdir()
    os.symlink(tmp_path / "nowhere", tmp_path / "dangling")
    os.symlink(tmp_path / "real", tmp_path / "live")
    with pytest.raises(OmniscsError, match="symbolic link"):
        check_output(tmp_path / "dangling")
    with pytest.raises(OmniscsError, match="symbolic link"):
        check_output(tmp_path / "live")
    with pytest.raises(OmniscsError, match="which does not exist"):
        check_output(tmp_path / "dangling" / "out")
    assert check_output(tmp_path / "real" / "out") == tmp_path / "real" / "out"
    with pytest.raises(OmniscsError, match="symbolic link"):
        with atomic_directory(tmp_path / "live", overwrite=True):
            pass
    assert _entries(tmp_path) == ["dangling", "live", "real"] and _entries(tmp_path / "real") == []


def test_names_too_long_and_folders_that_cannot_be_written_are_refused_before_any_work(tmp_path):
    with pytest.raises(OmniscsError, match="bytes; names here hold at most"):
        check_output(tmp_path / ("x" * 250))
    with pytest.raises(OmniscsError, match="bytes long; paths here hold"):
        check_output(tmp_path.joinpath(*["d" * 200] * 25))
    with pytest.raises(OmniscsError, match="cannot write in /proc"):
        check_output("/proc/omniscs-out")
    check_output(tmp_path / ("x" * 200))  # long, but fits with the temporary's room
    assert _entries(tmp_path) == []  # the writability probe leaves nothing


@pytest.mark.parametrize("argv", [
    ["world", "make", "--out", "{dangling}"],
    ["world", "make", "--out", "{dangling}/store"],
    ["world", "render", "{store}", "--out", "/proc/x.png"],
    ["world", "export", "{store}", "--format", "nuscenes", "--out", "{dangling}"],
])
def test_the_cli_refuses_such_outputs_in_one_line(argv, tmp_path, tmp_path_factory):
    os.symlink(tmp_path / "nowhere", tmp_path / "dangling")
    argv = [a.format(dangling=tmp_path / "dangling", store=synthetic_store(tmp_path_factory)) for a in argv]
    result = runner.invoke(app, argv)  # the entry point prints an OmniscsError as one line (tests/cli)
    assert isinstance(result.exception, OmniscsError), result.output
    assert "symbolic link" in str(result.exception) or "cannot write" in str(result.exception)
    assert not (tmp_path / "nowhere").exists()


def test_a_workspace_that_points_nowhere_is_refused_not_created_elsewhere(tmp_path):
    os.symlink(tmp_path / "elsewhere", tmp_path / "ws")
    with pytest.raises(OmniscsError, match="workspace .* symbolic link to .*elsewhere, which does not exist"):
        usable_workspace(tmp_path / "ws")
    result = runner.invoke(app, ["generate", "syn:straight:0", "--frames", "2", "--workspace", str(tmp_path / "ws")])
    assert isinstance(result.exception, OmniscsError) and "which does not exist" in str(result.exception)
    assert not (tmp_path / "elsewhere").exists()
    (tmp_path / "elsewhere").mkdir()  # a link to a folder is followed: the workspace is its target
    assert usable_workspace(tmp_path / "ws") == tmp_path / "elsewhere"


def test_catalog_tables_and_pool_models_that_lead_out_of_their_folder_are_refused(tmp_path):
    root = tmp_path / "catalog"
    root.mkdir()
    outside = tmp_path / "outside"
    (outside / "frames").mkdir(parents=True)
    os.symlink(outside / "frames", root / "frames")
    with pytest.raises(OmniscsError, match="leads out of"):
        catalog.query(root, "SELECT count(*) FROM frames")
    os.unlink(root / "frames")
    (root / "runs").mkdir()
    os.symlink(outside / "x.parquet", root / "runs" / "x.parquet")
    with pytest.raises(OmniscsError, match="catalog file .* leads out of"):
        catalog.query(root, "SELECT count(*) FROM runs")

    pool = Pool(tmp_path / "pool")
    model = pool.add(_model(), "car", "mesh", "sedan-0001")
    os.replace(tmp_path / "pool" / "models", outside / "models")
    os.symlink(outside / "models", tmp_path / "pool" / "models")
    with pytest.raises(OmniscsError, match="pool model folder .* leads out of"):
        pool.get(model)
