"""The omniscs CLI: user mistakes exit 2 with one line; info, preview and catalog query work."""
import json
import subprocess
import sys

import pytest
from typer.testing import CliRunner

from omniscs import catalog
from omniscs.cli import app
from omniscs.scene import load_scene
from omniscs.scene.summary import agent_rows

runner = CliRunner()


def run_cli(*args, cwd=None):
    """Run the real entry point in a subprocess, as a user would."""
    return subprocess.run([sys.executable, "-c", "from omniscs.cli import main; main()", *args],
                          capture_output=True, text=True, cwd=cwd, timeout=120)


def test_user_error_exits_2_with_one_line_and_no_traceback(tmp_path):
    proc = run_cli("scene", "info", str(tmp_path / "nowhere"))
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and "manifest.json is missing" in proc.stderr


def test_scene_info_json_describes_the_scene(tiny_scene):
    result = runner.invoke(app, ["scene", "info", str(tiny_scene), "--json"])
    assert result.exit_code == 0, result.output
    info = json.loads(result.output)
    assert info["scene_id"] == "tiny" and info["n_frames"] == 5 and info["n_tracks"] == 2
    assert info["cameras"] == {"CAM_FRONT": {"size": [64, 36]}}


def test_scene_preview_writes_both_pictures(tiny_scene, tmp_path):
    result = runner.invoke(app, ["scene", "preview", str(tiny_scene), "--out", str(tmp_path / "pv")])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "pv" / "contact_sheet.png").stat().st_size > 1000
    assert (tmp_path / "pv" / "bev.png").stat().st_size > 1000


@pytest.mark.parametrize("flag, check", [
    ("--json", lambda out: json.loads(out)[0]["n"] == 2),
    ("--csv", lambda out: out.splitlines() == ["category,n", "car,2"]),
])
def test_catalog_query_prints_json_and_csv(tiny_scene, tmp_path, flag, check):
    catalog.write_rows(catalog.catalog_root(tmp_path), "agents", "r", agent_rows(load_scene(tiny_scene)))
    result = runner.invoke(app, ["catalog", "query", "SELECT category, count(*) AS n FROM agents GROUP BY 1",
                                 "--workspace", str(tmp_path), flag])
    assert result.exit_code == 0, result.output
    assert check(result.output)


def test_bad_synthetic_source_is_refused_before_the_flow_starts(tmp_path):
    proc = run_cli("generate", "syn:straight", "--workspace", str(tmp_path))
    assert proc.returncode == 2 and "syn:TEMPLATE:SEED" in proc.stderr
