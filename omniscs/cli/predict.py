"""``omniscs predict detection / planning``: a model's results on a nuScenes dataroot (or a generated dataset), in
the files ``omniscs eval detection / planning`` read; the embedded proxies, a user's weights for them, or a user's
external model through a job template."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from omniscs.cli.common import check_out, console, progress_bars, workspace_option
from omniscs.errors import OmniscsError

app = typer.Typer(help="Run a model on a nuScenes dataroot or a generated dataset and write results that "
                       "`omniscs eval` reads: detection (nuScenes detection results JSON) and planning (waypoints "
                       "per keyframe).", no_args_is_help=True)

DATAROOT = typer.Option(None, help="nuScenes dataroot (holds VERSION/ with the tables); or --dataset.")
DATASET = typer.Option(None, help="A generated dataset (its id in the workspace, or its folder), exported for the "
                                  "run as `omniscs dataset export --format nuscenes` exports it (same sample "
                                  "tokens); or --dataroot.")
VERSION = typer.Option(None, help="Table version folder under --dataroot (default: the only one there; the "
                                  "factory's exports write v1.0-trainval).")
OUT = typer.Option(..., help="Results file to write (.json); refused if it exists unless --overwrite.")
SCENES = typer.Option([], "--scene", help="These scenes only (names or tokens; repeat; default all).")
WEIGHTS = typer.Option(None, help="proxy: a folder of the proxy's weights (e.g. a fine-tuned one under "
                                  "<workspace>/downstream/<model_id>/); default the shipped ones.")
MODEL = typer.Option("proxy", help="proxy (the embedded proxy model) or external (your model, run as a job).")
TEMPLATE = typer.Option(None, help="external: the job's command with {placeholders}: {dataset_root} {version} "
                                   "{task} {results} (the file the job must write), {work_dir}, {info_val} (with "
                                   "--dataset: UniAD's infos), {gpu_ids}, {n_gpus}.")
GPU_IDS = typer.Option("0", help="external: value of {gpu_ids}.")
TIMEOUT = typer.Option(6 * 3600.0, help="external: stop the job after this many seconds.")
OVERWRITE = typer.Option(False, help="Replace an existing --out.")


def _predict(task: str, dataroot: Optional[Path], dataset: Optional[str], version: Optional[str], out: Path,
             scene: list[str], weights: Optional[Path], model: str, external_template: Optional[str], gpu_ids: str,
             timeout_s: float, overwrite: bool, workspace: Optional[Path]) -> None:
    from omniscs.pipeline.predict import predict_external, predict_proxy

    if (dataroot is None) == (dataset is None):  # before any other check: the first thing a user gets wrong
        raise OmniscsError("name exactly one of --dataroot (a nuScenes dataroot) and --dataset (a generated dataset)")
    if model not in ("proxy", "external"):
        raise OmniscsError(f"--model is proxy or external; got {model!r}")
    if model == "external" and not external_template:
        raise OmniscsError("--model external needs --external-template (the job's command)")
    if model == "proxy" and external_template:
        raise OmniscsError("--external-template applies to --model external only")
    if model == "external" and weights is not None:
        raise OmniscsError("--weights applies to --model proxy only (an external job names its own checkpoint)")
    check_out(out, overwrite, suffix=".json")
    if weights is not None:  # a bad folder fails before an export or a run
        from omniscs.eval.detector import load_detector
        from omniscs.eval.planner import load_planner

        (load_detector if task == "detection" else load_planner)(weights)
    from omniscs.cli.evaluation import evaluated_dataroot

    fmt = "uniad" if model == "external" else "nuscenes"  # an external stack may want UniAD's infos of a dataset
    with progress_bars() as bars, evaluated_dataroot(dataroot, dataset, version, workspace, bars, fmt) as (root, ver):
        if model == "proxy":
            summary = predict_proxy(task, root, ver, out, scenes=scene or None, weights=weights,
                                    progress=bars.sink(f"predict {task}"))
        else:
            info_val = root.parent / "infos" / "nuscenes_infos_temporal_val.pkl" if dataset is not None else None
            summary = predict_external(task, external_template, root, ver, out, scenes=scene or None,
                                       values={"gpu_ids": gpu_ids, "n_gpus": len(gpu_ids.split(","))},
                                       timeout_s=timeout_s, info_val=info_val)
    what = (f"{summary['boxes']} boxes" if "boxes" in summary else
            f"{summary['trajectories']} trajectories ({summary['keyframes_with_map']} keyframes with a map)"
            if "trajectories" in summary else "results checked")
    console.print(f"wrote {out}: {task} results of {summary['samples']} samples, {what}, in {summary['seconds']:.1f} s")
    where = f"--dataroot {dataroot}" if dataroot is not None else f"--dataset {dataset}"
    console.print(f"then: omniscs eval {task} {where} --results {out}")


@app.command("detection")
def detection(dataroot: Optional[Path] = DATAROOT, dataset: Optional[str] = DATASET, version: Optional[str] = VERSION,
              out: Path = OUT, scene: list[str] = SCENES, weights: Optional[Path] = WEIGHTS, model: str = MODEL,
              external_template: Optional[str] = TEMPLATE, gpu_ids: str = GPU_IDS, timeout_s: float = TIMEOUT,
              overwrite: bool = OVERWRITE, workspace: Optional[Path] = workspace_option()) -> None:
    """3D boxes of every keyframe in the nuScenes detection results format (meta + results by sample_token), from
    the embedded proxy camera detector or your model."""
    _predict("detection", dataroot, dataset, version, out, scene, weights, model, external_template, gpu_ids,
             timeout_s, overwrite, workspace)


@app.command("planning")
def planning(dataroot: Optional[Path] = DATAROOT, dataset: Optional[str] = DATASET, version: Optional[str] = VERSION,
             out: Path = OUT, scene: list[str] = SCENES, weights: Optional[Path] = WEIGHTS, model: str = MODEL,
             external_template: Optional[str] = TEMPLATE, gpu_ids: str = GPU_IDS, timeout_s: float = TIMEOUT,
             overwrite: bool = OVERWRITE, workspace: Optional[Path] = workspace_option()) -> None:
    """Six waypoints at 0.5 s for every keyframe, in UniAD's planning frame ({'results': {sample_token:
    {'trajectory': [[x, y] x 6]}}}), from the embedded proxy planner or your model."""
    _predict("planning", dataroot, dataset, version, out, scene, weights, model, external_template, gpu_ids,
             timeout_s, overwrite, workspace)
