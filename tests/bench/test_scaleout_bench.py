"""The scale-out benchmark (``omniscs bench scaleout``) is Prefect-free: it runs whatever flow it is given (the CLI
passes ``generate_dataset``), once per set-up in a fresh workspace, and writes reports/scaleout/."""
import json
import time

from omniscs.bench.scaleout import STAGES, quick_config, run_scaleout_benchmark
from omniscs.pipeline.request import RunRequest


def test_the_benchmark_runs_the_flow_it_is_given_per_set_up_and_writes_its_folder(tmp_path):
    calls = []

    def fake_flow(request: RunRequest):
        calls.append(request.to_dict())
        time.sleep(0.01 * (3 - request.workers))  # two workers finish sooner
        scenes = [{"stages": {s: {"seconds": 1.0} for s in STAGES}} for _ in request.sources]
        return {"scenes": scenes, "failed": [], "dataset_id": f"ds-{request.workers}"}

    config = quick_config()
    result = run_scaleout_benchmark(tmp_path / "reports", tmp_path / "ws", fake_flow, config)
    assert [c["workers"] for c in calls] == [*config.workers, max(config.workers)]
    assert len({c["workspace"] for c in calls}) == len(calls)  # a fresh workspace per set-up
    assert all(c["sources"] == list(config.scenes) and c["task_runner"] == "dask" for c in calls)
    assert result["speedup"] > 1 and result["resume"]["killed"] == []  # no fit lock ever appeared: nothing killed
    folder = tmp_path / "reports" / "scaleout"
    assert sorted(p.name for p in folder.iterdir()) == ["report.json", "report.md", "report.png"]
    assert json.loads((folder / "report.json").read_text())["runs"][0]["dataset_id"] == f"ds-{config.workers[0]}"
