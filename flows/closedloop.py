"""The ``closed_loop_eval`` flow: a driving policy tested inside edited worlds. Each scenario (a scene's log or a
behaviour variant) is driven by the policy in its scene's fitted graph and scored (PDMS, EPDMS, HD-Score); one
``closed_loop_runs`` row per scenario and a ``runs`` row for the evaluation. A scenario that fails is recorded failed
and the others still run; the flow then ends failed."""
from __future__ import annotations

from prefect import flow, get_run_logger, unmapped

from omniscs.closedloop.epdms import EPDMSConfig
from omniscs.closedloop.simulator import ClosedLoopConfig
from omniscs.errors import OmniscsError, ValidationError
from omniscs.pipeline import closedloop as c
from omniscs.pipeline.records import new_run_id
from omniscs.pipeline.validate import check_run_id
from omniscs.storage import workspace_root
from flows.generate import _now_us, one_line
from flows.runners import check_runner, scene_task_runner
from tasks import closedloop as t
from tasks import downstream as td
from tasks import stages as ts


@flow(name="closed_loop_eval", log_prints=False)
def closed_loop_eval(scenarios: list[str], policy: str = "rule", workspace: str | None = None,
                     run_id: str | None = None, reactive: bool = False, max_steps: int | None = None,
                     cameras: list[str] | None = None, width: int | None = None,
                     out_dir: str | None = None, task_runner: str = "threads", workers: int | None = 1,
                     dask_address: str | None = None, ttc: str = "ours") -> dict:
    """Drive ``scenarios`` (``SCENE_ID/log`` or ``SCENE_ID/VARIANT_ID``) with ``policy`` (replay, rule, proxy,
    proxy:PATH or a DriveArena driver's http://HOST:PORT); ``reactive``: agents brake for the ego; ``cameras`` and
    ``width``: what is rendered (default: the fitted rig at its size); ``out_dir``: where the run folders go
    (default: the workspace's ``closedloop/<eval id>/``). Scenarios run on ``task_runner`` (``threads``: ``workers``
    at once, default one; ``dask``: a local cluster or ``dask_address``; see flows/runners.py). ``ttc``: how EPDMS
    scores time to collision, "ours" (PDMS's check) or "navsim" (NAVSIM's; see omniscs.closedloop.epdms)."""
    ws = str(workspace_root(workspace))
    run_id = check_run_id(run_id) or new_run_id()
    started = _now_us()
    settings = {"scenarios": scenarios, "policy": policy, "reactive": reactive, "max_steps": max_steps,
                "cameras": cameras, "width": width, "out_dir": out_dir, "task_runner": task_runner,
                "workers": workers, "dask_address": dask_address, "ttc": ttc}
    try:
        if not scenarios:
            raise ValidationError("name at least one scenario (SCENE_ID/log or SCENE_ID/VARIANT_ID)")
        for ref in scenarios:
            c.parse_ref(ref)
        check_runner(task_runner, workers, dask_address)
        config = ClosedLoopConfig(cameras=tuple(cameras) if cameras else None, width=width, reactive=reactive,
                                  outputs=("rgb", "depth"))
        epdms = EPDMSConfig(ttc=ttc)
        evaluated = c.settings_of(config, max_steps)
        if ttc != "ours":  # the default keeps the evaluation ids it had before EPDMS
            evaluated["ttc"] = ttc
        eval_id = c.eval_id_of(policy, scenarios, evaluated)
        with scene_task_runner(task_runner, workers, dask_address) as runner:
            futures = runner.map(t.run_scenario, {"workspace": unmapped(ws), "scenario": list(scenarios),
                                                  "policy": unmapped(policy), "eval_id": unmapped(eval_id),
                                                  "config": unmapped(config), "max_steps": unmapped(max_steps),
                                                  "out_dir": unmapped(out_dir), "epdms": unmapped(epdms)})
            records = [f.result() for f in futures]
        td.catalog(run_id, ws, records, writer="closedloop")
    except BaseException as exc:
        ts.catalog_run.fn(run_id, ws, "closed_loop_eval", "failed" if isinstance(exc, Exception) else "cancelled",
                          started, _now_us(), 0, settings, error=one_line(exc))
        raise
    failed = [f"{r.rows['closed_loop_runs'][0]['scenario_id']}: {r.info.get('error')}" for r in records
              if r.info.get("status") == "failed"]
    ts.catalog_run(run_id, ws, "closed_loop_eval", "failed" if failed else "completed", started, _now_us(),
                   len({ref.split('/')[0] for ref in scenarios}), settings, error="; ".join(failed) or None)
    if failed:
        get_run_logger().error("closed-loop scenarios failed: %s", "; ".join(failed))
        raise OmniscsError(f"run {run_id}: " + "; ".join(failed))
    return {"run_id": run_id, "eval_id": eval_id, "workspace": ws, "runs": [r.info for r in records]}
