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


def test_scene_info_refuses_a_store_whose_image_was_swapped_with_its_hash(tiny_scene, tmp_path):
    import shutil
    from pathlib import Path

    import cv2
    import numpy as np

    from omniscs.errors import OmniscsError
    from omniscs.scene.store import FILES, MANIFEST, file_sha256

    store = Path(shutil.copytree(tiny_scene, tmp_path / "store"))
    rel = "images/CAM_FRONT/000001.png"
    (store / rel).write_bytes(cv2.imencode(".jpg", np.zeros((36, 64, 3), np.uint8))[1].tobytes())
    manifest = json.loads((store / MANIFEST).read_text())
    manifest[FILES][rel] = [(store / rel).stat().st_size, file_sha256(store / rel)]
    (store / MANIFEST).write_text(json.dumps(manifest))
    result = runner.invoke(app, ["scene", "info", str(store), "--json"])
    assert isinstance(result.exception, OmniscsError) and "not a PNG image" in str(result.exception)
    assert runner.invoke(app, ["scene", "info", str(store), "--json", "--no-verify"]).exit_code == 0


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
    result = runner.invoke(app, ["catalog", "query", "SELECT category, count(*) AS n FROM agents_raw GROUP BY 1",
                                 "--workspace", str(tmp_path), flag])
    assert result.exit_code == 0, result.output
    assert check(result.output)


def test_bad_synthetic_source_is_refused_before_the_flow_starts(tmp_path):
    proc = run_cli("generate", "syn:straight", "--workspace", str(tmp_path))
    assert proc.returncode == 2 and "syn:TEMPLATE:SEED" in proc.stderr


def test_world_render_applies_edits_to_the_ground_truth_world(tmp_path):
    from omniscs.scene import SyntheticSource, write_synthetic_scene

    src = SyntheticSource(template="straight_parked_truck", seed=3, n_frames=1, n_cameras=1, width=96, height=54)
    scene_dir = write_synthetic_scene(src, tmp_path / "s")
    scene = load_scene(scene_dir)
    big = int(scene.boxes.sort_values("visible_pixels").iloc[-1].track_id)
    plain, removed = tmp_path / "plain.png", tmp_path / "removed.png"
    assert runner.invoke(app, ["world", "render", str(scene_dir), "--out", str(plain)]).exit_code == 0
    edits = tmp_path / "edits.json"
    edits.write_text(json.dumps([{"op": "remove", "track_id": big}]))
    result = runner.invoke(app, ["world", "render", str(scene_dir), "--out", str(removed), "--edit", f"@{edits}"])
    assert result.exit_code == 0, result.output
    import cv2
    a, b = cv2.imread(str(plain)), cv2.imread(str(removed))
    np_changed = (abs(a.astype(int) - b.astype(int)).sum(axis=2) > 30).mean()
    assert np_changed > 0.02  # the largest visible object is gone, background shows through
    np_same = (cv2.imread(str(plain)) == scene.image("CAM_FRONT", 0)[..., ::-1]).all(axis=2).mean()
    assert np_same > 0.99     # re-rendering the unedited world reproduces the stored image


def test_world_render_refuses_a_bad_edit_with_one_line(tiny_scene, tmp_path):
    proc = run_cli("world", "render", str(tiny_scene), "--out", str(tmp_path / "x.png"))
    assert proc.returncode == 2 and "not a synthetic scene" in proc.stderr


def test_comma_lists_parse_each_item_or_fail_in_one_line():
    from omniscs.cli.common import comma_list, seeds
    from omniscs.errors import OmniscsError

    assert comma_list("1, 2,,3", int) == (1, 2, 3) and comma_list(None) == () and seeds("4") == (4,)
    with pytest.raises(OmniscsError, match="comma-separated list like 0,1,2"):
        seeds("1,x")
    with pytest.raises(OmniscsError, match="at least one"):
        seeds(" , ")


def test_a_bad_generate_request_fails_before_the_flow_starts(tmp_path):
    proc = run_cli("generate", "syn:straight:0", "--fit-preset", "fastest", "--workspace", str(tmp_path / "ws"))
    assert proc.returncode == 2 and "--fit-preset (fit_preset: Input should be" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "ws" / "scenes").exists()
