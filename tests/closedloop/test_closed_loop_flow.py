"""The closed_loop_eval flow over a workspace (a scene, its fitted graph, a behaviour variant): one
closed_loop_runs row per scenario and a runs row; a scenario that cannot run is recorded failed without stopping
the others; the CLI refuses a bad scenario before Prefect starts."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from omniscs import catalog
from omniscs.errors import OmniscsError
from omniscs.pipeline import layout


def test_closed_loop_eval_catalogues_each_scenario_and_the_run(prefect_harness, world, workspace):
    from flows.closedloop import closed_loop_eval

    sid = world[0].scene_id
    out = closed_loop_eval([f"{sid}/log", f"{sid}/stop"], policy="replay", workspace=str(workspace), run_id="cl1",
                           width=64)
    rows = catalog.query(layout.catalog_root(workspace),
                         "SELECT scenario_id, kind, status, reason, pdms, epdms, hd_score, collision, run_path "
                         "FROM closed_loop_runs WHERE run_id = 'cl1' ORDER BY scenario_id").to_pylist()
    assert [r["scenario_id"] for r in rows] == [f"{sid}/log", f"{sid}/stop"]
    log_row, stop_row = rows
    assert log_row["kind"] == "log" and log_row["status"] == "ok" and not log_row["collision"]
    assert stop_row["kind"] == "behavior" and stop_row["reason"] == "collision" and stop_row["pdms"] < log_row["pdms"]
    assert stop_row["epdms"] < log_row["epdms"] and log_row["epdms"] > 0.9
    for r in rows:
        assert layout.closedloop_folder(workspace, out["eval_id"]) in Path(r["run_path"]).parents
        assert json.loads((Path(r["run_path"]) / "run.json").read_text())["scores"]
    run = catalog.query(layout.catalog_root(workspace),
                        "SELECT flow, status FROM runs WHERE run_id = 'cl1'").to_pylist()
    assert run == [{"flow": "closed_loop_eval", "status": "completed"}]


def test_a_scenario_that_cannot_run_is_recorded_failed_and_the_others_still_run(prefect_harness, world, workspace):
    from flows.closedloop import closed_loop_eval

    sid = world[0].scene_id
    with pytest.raises(OmniscsError, match="no behaviour variant v999"):
        closed_loop_eval([f"{sid}/v999", f"{sid}/log"], policy="rule", workspace=str(workspace), run_id="cl2",
                         max_steps=3, width=64)
    rows = {r["scenario_id"]: r for r in catalog.query(
        layout.catalog_root(workspace), "SELECT scenario_id, status, error, steps FROM closed_loop_runs_by_run "
                                        "WHERE run_id = 'cl2'").to_pylist()}
    assert rows[f"{sid}/v999"]["status"] == "failed" and "v999" in rows[f"{sid}/v999"]["error"]
    assert rows[f"{sid}/log"]["status"] == "ok" and rows[f"{sid}/log"]["steps"] == 3
    run = catalog.query(layout.catalog_root(workspace), "SELECT status FROM runs WHERE run_id = 'cl2'").to_pylist()
    assert run == [{"status": "failed"}]


@pytest.mark.slow  # 15 s (the flow starts before the refusal): make test's five minutes
def test_the_cli_refuses_an_unknown_scene_or_policy_in_one_line(workspace, world):
    for args in (["closedloop", "run", "no-such-scene/log"],
                 ["closedloop", "run", f"{world[0].scene_id}/log", "--policy", "greedy"],
                 ["closedloop", "run", "a/b/c"]):
        proc = subprocess.run([sys.executable, "-c", "from omniscs.cli import main; main()", *args,
                               "--workspace", str(workspace)], capture_output=True, text=True, timeout=120)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr
        assert proc.stderr.strip().count("\n") == 0 and proc.stderr.startswith("error:"), proc.stderr


def test_a_bad_camera_run_id_or_width_is_refused_before_the_flow_starts(workspace, world, monkeypatch):
    from typer.testing import CliRunner

    import flows.closedloop
    from omniscs.cli import app
    from omniscs.errors import OmniscsError

    monkeypatch.setattr(flows.closedloop, "closed_loop_eval", lambda *a, **k: pytest.fail("the flow started"))
    ref = f"{world[0].scene_id}/log"
    for extra, message in ((["--camera", "CAM_NOSE"], "--camera CAM_NOSE: not a camera of scene"),
                           (["--run-id", "../x"], "run id")):
        result = CliRunner().invoke(app, ["closedloop", "run", ref, "--workspace", str(workspace), *extra])
        assert isinstance(result.exception, OmniscsError) and message in str(result.exception), result.output
    result = CliRunner().invoke(app, ["closedloop", "run", ref, "--workspace", str(workspace), "--width", "-5"])
    assert result.exit_code == 2 and "--width" in result.output
    result = CliRunner().invoke(app, ["closedloop", "run", ref, "--workspace", str(workspace), "--ttc", "carla"])
    assert result.exit_code == 2 and "--ttc" in result.output


def test_the_serve_command_serves_a_workspace_scenario_to_hugsims_client(workspace, world, monkeypatch):
    import socket
    import time

    import numpy as np
    import requests

    monkeypatch.setenv("IN_HF_SPACE", "false")
    from hugsim_client import HugsimClient

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-c", "from omniscs.cli import main; main()", "closedloop", "serve",
                             "--scenario", f"{world[0].scene_id}/log", "--token", "secret", "--port", str(port),
                             "--width", "64", "--workspace", str(workspace)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        url = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 90
        while True:
            try:
                if requests.get(url + "/", timeout=2).status_code == 200:
                    break
            except requests.ConnectionError:
                pass
            assert proc.poll() is None, proc.stderr.read()
            assert time.monotonic() < deadline, "the server did not answer within 90 s"
            time.sleep(0.3)
        client = HugsimClient(host=url, api_token="secret")
        client.reset_env()
        state = client.execute_action(np.array([[0.0, 3.0 * k] for k in range(1, 7)]))
        assert state.state.info["step"] == 1 and state.state.obs["rgb"]["CAM_FRONT"].shape[1] == 64
        assert requests.post(url + "/reset", headers={"auth-token": "wrong"}, timeout=10).status_code == 401
    finally:
        proc.terminate()
        proc.wait(timeout=30)
