"""``omniscs eval detection / planning``: nuScenes detection metrics and UniAD's planning metrics of a results file
against a nuScenes dataroot (an export of a generated dataset, or the real dataset)."""
from __future__ import annotations

import contextlib
import json
from pathlib import Path
from typing import Iterator, Optional

import typer

from omniscs.cli.common import Bars, console, print_error, progress_bars, workspace_option
from omniscs.errors import OmniscsError

app = typer.Typer(help="Evaluate driving-model outputs on a nuScenes dataroot: detection (mAP, NDS) and planning "
                       "(L2, collision rate).", no_args_is_help=True)

DATAROOT = typer.Option(None, help="nuScenes dataroot (holds VERSION/ with the tables); or --dataset.")
DATASET = typer.Option(None, help="A generated dataset (its id in the workspace, or its folder), exported for the "
                                  "run as `omniscs dataset export --format nuscenes` exports it; or --dataroot.")
VERSION = typer.Option(None, help="Table version folder under the dataroot (default: the only one there; the "
                                  "factory's exports write v1.0-trainval).")
SCENES = typer.Option([], "--scene", help="Evaluate these scenes only (names or tokens; repeat; default all).")


@contextlib.contextmanager
def evaluated_dataroot(dataroot: Optional[Path], dataset: Optional[str], version: Optional[str],
                       workspace: Optional[Path], bars: Bars, fmt: str = "nuscenes") -> Iterator[tuple[Path, str]]:
    """(dataroot, version) to evaluate (or predict) on: --dataroot with its version (the only one there when not
    named; said on stderr), or --dataset exported for the block as ``fmt`` (``pipeline.predict.dataset_dataroot``;
    its progress on ``bars``, the command's one set of bars)."""
    from omniscs.eval.nuscenes_io import resolve_version

    if (dataroot is None) == (dataset is None):
        raise OmniscsError("name exactly one of --dataroot (a nuScenes dataroot) and --dataset (a generated dataset)")
    if dataset is not None:
        from omniscs.cli.dataset import dataset_path
        from omniscs.pipeline.predict import dataset_dataroot

        if version is not None:
            raise OmniscsError("--version applies to --dataroot (a dataset is exported as v1.0-trainval)")
        source = dataset_path(dataset, workspace)
        with dataset_dataroot(source, fmt, progress=bars.sink(f"export {source.name}")) as found:
            try:
                yield found
            except OmniscsError as exc:  # name the dataset, not the temporary export that is gone with the run
                raise type(exc)(str(exc).replace(str(found[0] / found[1]), f"dataset {source.name}")
                                .replace(str(found[0]), f"dataset {source.name}")) from None
        return
    detected = resolve_version(dataroot, version)
    if version is None:
        print_error(f"version {detected} (the only one in {dataroot})", label="note", style="cyan")
    yield dataroot, detected


@app.command("detection")
def detection(
    dataroot: Optional[Path] = DATAROOT,
    dataset: Optional[str] = DATASET,
    version: Optional[str] = VERSION,
    results: Path = typer.Option(..., help="Results in the nuScenes detection results format (JSON)."),
    scene: list[str] = SCENES,
    classes: list[str] = typer.Option([], "--class", help="Average mAP and NDS over these classes only (repeat; "
                                                          "default the ten nuScenes classes, absent ones AP 0)."),
    camera_view: bool = typer.Option(False, "--camera-view", help="Score only the boxes (ground truth and "
                                     "predictions) a camera of the sample sees: for rigs whose cameras do not look all "
                                     "round, such as the factory's three front cameras."),
    as_json: bool = typer.Option(False, "--json", help="Print the metrics as one JSON object."),
    workspace: Optional[Path] = workspace_option(),
) -> None:
    """mAP, the true-positive errors and NDS by the nuScenes protocol (centre distance 0.5/1/2/4 m)."""
    from omniscs.eval.detection import DETECTION_NAMES, DetectionConfig
    from omniscs.eval.nuscenes_io import evaluate_detection_results

    config = DetectionConfig(class_names=tuple(classes) or DETECTION_NAMES)
    with progress_bars() as bars, evaluated_dataroot(dataroot, dataset, version, workspace, bars) as (root, ver):
        metrics, info = evaluate_detection_results(root, ver, results, scenes=scene or None, config=config,
                                                   camera_view=camera_view)
    out = {**metrics.to_dict(), "n_samples": info["n_samples"], "camera_view": camera_view}
    if as_json:
        print(json.dumps(out))
        return
    from rich.table import Table

    table = Table(title=f"detection: mAP {out['mAP']:.4f}  NDS {out['NDS']:.4f}  ({info['n_samples']} samples"
                        f"{', boxes in the cameras view' if camera_view else ''})")
    for col in ("class", "GT", "pred", *(f"AP@{t:g}" for t in config.dist_ths), "AP", "ATE", "ASE", "AOE", "AVE",
                "AAE"):
        table.add_column(col, justify="left" if col == "class" else "right")
    for name, c in out["classes"].items():
        errs = [c["tp_errors"][m] for m in ("trans_err", "scale_err", "orient_err", "vel_err", "attr_err")]
        table.add_row(name, str(c["n_gt"]), str(c["n_pred"]), *(f"{v:.3f}" for v in c["AP"].values()),
                      f"{c['mean_AP']:.3f}", *("n/a" if e is None else f"{e:.3f}" for e in errs))
    console.print(table)


@app.command("planning")
def planning(
    dataroot: Optional[Path] = DATAROOT,
    dataset: Optional[str] = DATASET,
    version: Optional[str] = VERSION,
    results: Path = typer.Option(..., help="Planned trajectories: {'results': {sample_token: {'trajectory': "
                                           "[[x, y] x 6]}}} in UniAD's frame (x right, y forward, at the LiDAR)."),
    scene: list[str] = SCENES,
    convention: Optional[str] = typer.Option(None, help="Print only this horizon convention: uniad (the value at "
                                                        "1/2/3 s) or stp3 (the mean up to it); default both."),
    as_json: bool = typer.Option(False, "--json", help="Print the metrics as one JSON object."),
    workspace: Optional[Path] = workspace_option(),
) -> None:
    """L2 and collision rate (obj_box_col) at 1/2/3 s, as UniAD computes them."""
    from omniscs.eval.nuscenes_io import evaluate_planning_results
    from omniscs.eval.planning import CONVENTIONS, HORIZONS, STEP_S, STEPS

    if convention is not None and convention not in CONVENTIONS:
        raise typer.BadParameter(f"one of {', '.join(CONVENTIONS)}", param_hint="--convention")

    def coverage(n_full: int, n_keyframes: int) -> None:  # said before the metrics are computed (none: an error)
        if n_full:
            print_error(f"{n_full} of {n_keyframes} keyframes have the {STEPS * STEP_S:g} s of future the planning "
                        "metrics need; the others are left out", label="note", style="cyan")

    with progress_bars() as bars, evaluated_dataroot(dataroot, dataset, version, workspace, bars) as (root, ver):
        out = evaluate_planning_results(root, ver, results, scenes=scene or None, on_coverage=coverage)
    if as_json:
        print(json.dumps(out))
        return
    from rich.table import Table

    table = Table(title=f"planning: {out['n_samples']} keyframes ({out['n_short_future']} without a full future "
                        "left out)")
    table.add_column("metric")
    for h in HORIZONS:
        table.add_column(h, justify="right")
    for conv in [convention] if convention else CONVENTIONS:
        table.add_row(f"L2 (m), {conv}", *(f"{v:.3f}" for v in out[conv]["L2"].values()))
        table.add_row(f"collision (%), {conv}", *(f"{100 * v:.2f}" for v in out[conv]["obj_box_col"].values()))
    console.print(table)


def finetune(
    datasets: list[str] = typer.Argument(..., help="Ids of generated datasets in the workspace (train data)."),
    model: str = typer.Option("proxy", help="proxy (the embedded proxies, see --task) or external (a job command)."),
    test_dataset: list[str] = typer.Option([], "--test-dataset", help="Evaluate on these datasets (repeat; default "
                                                                      "the training datasets: a fit, not a test)."),
    external_template: Optional[str] = typer.Option(None, help="external: the job's command with {placeholders} "
                                                                "({dataset_root}, {info_train}, {info_val}, "
                                                                "{work_dir}, {gpu_ids}, ...)."),
    gpu_ids: str = typer.Option("0", help="external: value of {gpu_ids}."),
    timeout_s: float = typer.Option(6 * 3600.0, help="external: stop the job after this many seconds."),
    workspace: Optional[Path] = typer.Option(None, help="Workspace root (default $OMNISCS_HOME or ./omniscs-data)."),
    run_id: Optional[str] = typer.Option(None, help="Run id (default: time-stamped)."),
    task: list[str] = typer.Option([], "--task", help="proxy: planning (the proxy planner, default) and/or "
                                                      "detection (the proxy camera detector); repeat for both."),
    rehearse: list[Path] = typer.Option([], "--rehearse", help="detection: a nuScenes dataroot the base detector "
                                                               "was trained on, mixed into the fine-tuning so it "
                                                               "does not forget it (repeat; the shipped detector's: "
                                                               "omniscs pretrained train detector)."),
    planner_rehearsal: bool = typer.Option(True, "--planner-rehearsal/--no-planner-rehearsal",
                                           help="planning: mix in the logs the base planner was trained on (remade "
                                                "from its training record) instead of the datasets' source logs."),
) -> None:
    """Fine-tune on generated datasets and evaluate (the finetune_evaluate flow); results go to the catalog
    (downstream_models, evaluations)."""
    import os

    from omniscs.cli.prefect_api import prefect_api
    from omniscs.pipeline.downstream import dataset_paths
    from omniscs.storage import workspace_path

    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    if model not in ("proxy", "external"):
        raise typer.BadParameter("proxy or external", param_hint="--model")
    if model == "external" and not external_template:
        raise typer.BadParameter("needed with --model external", param_hint="--external-template")
    ws = workspace_path(workspace)
    dataset_paths(ws, list(datasets) + list(test_dataset))  # unknown ids fail here, before Prefect starts
    from omniscs.pipeline.downstream import dataroot_version

    for root in rehearse:
        dataroot_version(root)  # and so does a folder that is not a dataroot
    from flows.downstream import finetune_evaluate

    with prefect_api():
        out = finetune_evaluate(list(datasets), model=model, test_dataset_ids=list(test_dataset) or None,
                                workspace=str(ws), run_id=run_id, external_template=external_template,
                                external_values={"gpu_ids": gpu_ids, "n_gpus": len(gpu_ids.split(","))},
                                external_timeout_s=timeout_s, tasks=list(task) or None,
                                detector_rehearsal=[str(r) for r in rehearse] or None,
                                planner_rehearsal=planner_rehearsal)
    console.print(f"run {out['run_id']}: " + ", ".join(f"{m.get('model_id')} ({m.get('status', 'evaluated')})"
                                                    for m in out["models"]))
    console.print(f"see: omniscs catalog query \"SELECT model_id, split, metric, horizon, value FROM evaluations "
                  f"WHERE run_id = '{out['run_id']}'\"")
