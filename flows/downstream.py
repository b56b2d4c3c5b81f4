"""The downstream flows: what driving models make of generated datasets.

``finetune_evaluate``: the proxy planner fine-tuned on datasets, then the shipped base and the fine-tuned planner
evaluated on test datasets (behaviour-SCS and original examples); or an external job (UniAD) on the datasets, its
printed metrics read back. ``evaluate``: one planner on datasets. Both write ``downstream_models`` and
``evaluations`` rows and a ``runs`` row; the datasets may be named, or found from the ``generate_dataset`` flow run
that made them (``upstream_flow_run``: what a deployment trigger on its ``prefect.flow-run.Completed`` passes).
"""
from __future__ import annotations

from prefect import flow, get_run_logger

from omniscs.errors import OmniscsError, ValidationError
from omniscs.pipeline import downstream as d
from omniscs.pipeline.records import StageRecord, new_run_id
from omniscs.pipeline.validate import check_run_id
from omniscs.storage import workspace_root
from flows.generate import _now_us, one_line
from tasks import downstream as t
from tasks import stages as ts

MODELS = ("proxy", "external")
#: What the proxies can be fine-tuned and evaluated for.
TASKS = ("planning", "detection")


def _datasets(ws: str, dataset_ids: list[str] | None, upstream_flow_run: str | None) -> list[str]:
    if dataset_ids:
        return list(dataset_ids)
    if upstream_flow_run:
        return d.datasets_of_flow_run(ws, upstream_flow_run)
    raise ValidationError("name the datasets (dataset_ids) or the generate_dataset flow run that made them "
                          "(upstream_flow_run)")


@flow(name="finetune_evaluate", log_prints=False)
def finetune_evaluate(dataset_ids: list[str] | None = None, model: str = "proxy",
                      test_dataset_ids: list[str] | None = None, workspace: str | None = None,
                      run_id: str | None = None, upstream_flow_run: str | None = None,
                      external_template: str | None = None, external_values: dict | None = None,
                      external_timeout_s: float = 6 * 3600.0, external_export: str | None = "uniad",
                      tasks: list[str] | None = None, detector_rehearsal: list[str] | None = None,
                      planner_rehearsal: bool = True) -> dict:
    """Fine-tune and evaluate on ``dataset_ids`` (or the datasets of ``upstream_flow_run``). ``model="proxy"``:
    the embedded proxies of ``tasks`` (default ``["planning"]``; ``"detection"``: the proxy camera detector, made for
    datasets with appearance variants), each evaluated before (base) and after fine-tuning on ``test_dataset_ids``
    (default: the training datasets themselves, then a fit to the training data, not a test). ``model="external"``:
    ``external_template`` run as a job (``omniscs.eval.external``) on the exported datasets. Returns the run id,
    model records and evaluation ids and the comparison plot of its evaluations
    (``<workspace>/evaluations/<run_id>/comparison.png``); a model that fails is recorded failed and the run ends
    failed.
    ``detector_rehearsal``: nuScenes dataroots the base detector was trained on, mixed into its fine-tuning;
    ``planner_rehearsal``: the planner's fine-tuning mixes in the logs its base was trained on (remade from its
    training record) instead of the datasets' source logs."""
    ws = str(workspace_root(workspace))
    run_id = check_run_id(run_id) or new_run_id()
    started = _now_us()
    config = {"dataset_ids": dataset_ids, "model": model, "test_dataset_ids": test_dataset_ids,
              "upstream_flow_run": upstream_flow_run, "external_template": external_template, "tasks": tasks,
              "detector_rehearsal": detector_rehearsal, "planner_rehearsal": planner_rehearsal}
    records: list[StageRecord] = []
    try:
        if model not in MODELS:
            raise ValidationError(f"model must be one of {MODELS}; got {model!r}")
        datasets = _datasets(ws, dataset_ids, upstream_flow_run)
        d.dataset_paths(ws, datasets)
        wanted = list(tasks or ["planning"])
        unknown = [k for k in wanted if k not in TASKS]
        if unknown or not wanted:
            raise ValidationError(f"tasks must be some of {TASKS}; got {wanted}")
        if model == "proxy":
            tests = list(test_dataset_ids or datasets)
            if "planning" in wanted:
                tuned = t.finetune(datasets, ws, planner_rehearsal)
                records.append(tuned)
                records.append(t.evaluate(None, tests, ws, "base"))
                if tuned.info.get("status") == "trained":
                    records.append(t.evaluate(tuned, tests, ws, tuned.info["model_id"]))
            if "detection" in wanted:
                tuned = t.finetune_detector(datasets, ws, detector_rehearsal)
                records.append(tuned)
                records.append(t.evaluate_detector(None, tests, ws, "base"))
                records.append(t.evaluate_detector(tuned, tests, ws, tuned.info["model_id"]))
        else:
            if not external_template:
                raise ValidationError("model='external' needs external_template (a command with placeholders)")
            records.append(t.external(external_template, datasets, ws, external_values or {}, external_timeout_s,
                                      external_export))
        t.catalog(run_id, ws, records)
        plot = t.comparison_plot(run_id, ws, records)
    except BaseException as exc:
        status = "failed" if isinstance(exc, Exception) else "cancelled"
        ts.catalog_run.fn(run_id, ws, "finetune_evaluate", status, started, _now_us(), 0, config,
                          error=one_line(exc))
        raise
    failed = [r.info.get("error") or "no model to evaluate" for r in records if r.info.get("status") == "failed"]
    ts.catalog_run(run_id, ws, "finetune_evaluate", "failed" if failed else "completed", started, _now_us(), 0, config,
                   error="; ".join(failed) or None)
    if failed:
        get_run_logger().error("downstream model failed: %s", "; ".join(failed))
        raise OmniscsError(f"run {run_id}: " + "; ".join(failed))
    return {"run_id": run_id, "workspace": ws, "datasets": datasets, "models": [r.info for r in records],
            "plot": plot}


@flow(name="evaluate", log_prints=False)
def evaluate(model: str, dataset_ids: list[str], workspace: str | None = None, run_id: str | None = None) -> dict:
    """Evaluate one planner on datasets: ``model`` is ``proxy-planner-base`` (the shipped proxy) or the id of a
    fine-tuned proxy planner in the workspace (``downstream/<id>/``)."""
    from omniscs.pipeline import layout

    ws = str(workspace_root(workspace))
    run_id = check_run_id(run_id) or new_run_id()
    started = _now_us()
    config = {"model": model, "dataset_ids": dataset_ids}
    try:
        if model == d.BASE_MODEL_ID:
            record = None
        else:
            path = layout.downstream_folder(ws, model) / "planner"
            if not path.is_dir():
                raise ValidationError(f"no downstream model {model} in {ws} (see the downstream_models table)")
            record = StageRecord("finetune", "-", str(path), info={"model_id": model, "status": "trained"})
        result = t.evaluate(record, dataset_ids, ws, model)
        t.catalog(run_id, ws, [result])
        plot = t.comparison_plot(run_id, ws, [result])
    except BaseException as exc:
        ts.catalog_run.fn(run_id, ws, "evaluate", "failed" if isinstance(exc, Exception) else "cancelled", started,
                          _now_us(), 0, config, error=one_line(exc))
        raise
    ts.catalog_run(run_id, ws, "evaluate", "completed", started, _now_us(), 0, config)
    return {"run_id": run_id, "eval_id": result.info["eval_id"], "model_id": result.info["model_id"], "plot": plot}
