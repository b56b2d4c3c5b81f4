"""``omniscs dataset build / info / export``: annotated SCS datasets, made by the ``generate_dataset`` flow."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from omniscs.cli.common import check_out, console, progress_bars, show_dataset, workspace_option
from omniscs.errors import OmniscsError

app = typer.Typer(help="Annotated SCS datasets: build (the generate_dataset flow with render + annotate), "
                       "inspect, export to nuScenes, UniAD or OpenSCENARIO.", no_args_is_help=True)


def dataset_path(dataset: str, workspace: Optional[Path]) -> Path:
    """A dataset named by its folder or by its id in the workspace (``<workspace>/datasets/<id>``)."""
    from omniscs.annotate.dataset import CARD_JSON
    from omniscs.pipeline import layout
    from omniscs.storage import workspace_path

    path = Path(dataset)
    if not (path / CARD_JSON).is_file():
        from omniscs.ids import is_safe_id

        if is_safe_id(dataset):
            path = layout.dataset_folder(workspace_path(workspace), dataset)
    if not (path / CARD_JSON).is_file():
        raise OmniscsError(f"{dataset} is not a dataset (no {CARD_JSON} in {path}); build one with "
                           "`omniscs dataset build` or name its folder")
    return path


@app.command("build")
def build(
    sources: list[str] = typer.Argument(..., help="syn:TEMPLATE:SEED[:LIGHTING], FORMAT:DATAROOT[:SCENE] or "
                                                  "scene-store paths."),
    fit_preset: str = typer.Option("fast", help="Scene-graph preset: fast, balanced or accurate."),
    behavior_variants: int = typer.Option(2, help="Behaviour-level SCS variants per scene (at least 1)."),
    out: Optional[str] = typer.Option(None, help="Dataset id: its folder is <workspace>/datasets/<id> "
                                                 "(default ds-<content hash>: the same inputs give the same id)."),
    workspace: Optional[Path] = workspace_option(),
    run_id: Optional[str] = typer.Option(None, help="Run id (default: time-stamped)."),
    frames: int = typer.Option(40, help="Synthetic sources: frames at 10 Hz."),
    cameras: int = typer.Option(3, help="Synthetic sources: cameras, 1 to 6."),
    width: int = typer.Option(480, help="Synthetic sources: image width."),
    height: int = typer.Option(270, help="Synthetic sources: image height."),
    behavior_preset: str = typer.Option("balanced", help="Behaviour optimisation preset."),
    device: str = typer.Option("cpu", help="Compute device of the scene graph and behaviour optimisation."),
    keep_failed: bool = typer.Option(False, help="Put variants that fail the quality gates into the dataset too, "
                                                 "marked (by default they stay in the workspace and the catalog)."),
    variant_budget: int = typer.Option(3, help="Candidates tried per requested variant until as many as "
                                               "requested pass the quality gates."),
) -> None:
    """Generate, render and annotate variants of every source; those that pass the quality gates are gathered as
    one dataset (and catalogued)."""
    from omniscs.cli.generate import run_generate

    result = run_generate({"sources": list(sources), "workspace": str(workspace) if workspace else None,
                           "run_id": run_id, "n_frames": frames, "n_cameras": cameras, "width": width,
                           "height": height, "previews": False, "fit_preset": fit_preset,
                           "behavior_variants": behavior_variants, "behavior_preset": behavior_preset,
                           "device": device, "annotate": True, "dataset_id": out, "keep_failed": keep_failed,
                           "variant_budget": variant_budget})
    show_dataset(Path(result["dataset_path"]))


@app.command("info")
def info(dataset: str = typer.Argument(..., help="Dataset folder or id."),
         workspace: Optional[Path] = workspace_option()) -> None:
    """What a dataset holds: counts, fidelity, variants, where its card and preview are."""
    show_dataset(dataset_path(dataset, workspace))


def variant_stores(dataset: str, workspace: Optional[Path]) -> tuple[Path, list[Path]]:
    """The variant stores to export: a dataset's (named by folder or id) or those of a variants folder that holds
    rendered stores under ``scenes/`` (``omniscs scs appearance --out``)."""
    from omniscs.annotate.dataset import CARD_JSON, SCENES
    from omniscs.scene.store import MANIFEST

    folder = Path(dataset)
    if not (folder / CARD_JSON).is_file() and (folder / SCENES).is_dir():
        stores = sorted(p for p in (folder / SCENES).iterdir() if (p / MANIFEST).is_file())
        if not stores:
            raise OmniscsError(f"{folder / SCENES} holds no variant store (no folder with {MANIFEST}); render the "
                               "variants first")
        return folder, stores
    if not (folder / CARD_JSON).is_file() and (folder / "variants.json").is_file():
        raise OmniscsError(f"{folder} holds behaviour variants that were never rendered (variants.json, no "
                           f"{SCENES}/): export them with --format openscenario --scene STORE (the scene store they "
                           "were made from), or build a dataset of them (`omniscs dataset build`) and export that")
    path = dataset_path(dataset, workspace)
    return path, sorted(p for p in (path / SCENES).iterdir() if p.is_dir())


@app.command("export")
def export(dataset: str = typer.Argument(..., help="Dataset folder or id, or a variants folder with rendered "
                                                    "stores (scenes/)."),
           format: str = typer.Option(..., "--format", help="nuscenes, uniad or openscenario (.xosc + .xodr)."),
           out: Path = typer.Option(..., help="Output folder."),
           overwrite: bool = typer.Option(False, help="Replace --out if omniscs wrote it."),
           location: str = typer.Option("boston-seaport", help="nuScenes map location of scenes that carry none "
                                                               "(procedural scenes); recorded logs keep their own."),
           box_convention: str = typer.Option("v1", help="uniad: gt_boxes as UniAD main writes them (v1: w, l, h, "
                                                         "-yaw - pi/2) or as UniAD v2.0 does (v2)."),
           val_scene: list[str] = typer.Option([], help="uniad: a variant scene id for the val pickle (repeat the "
                                                        "option); the others go to train."),
           keep_unseen: bool = typer.Option(False, help="Also label boxes no sensor captured (no LiDAR point, no "
                                                        "visible pixel) before an object is first seen or after it "
                                                        "is last seen, and objects never seen."),
           nuscenes_maps: Optional[Path] = typer.Option(None, help="openscenario: a nuScenes dataroot whose "
                                                                   "maps/expansion give variants of recorded nuScenes "
                                                                   "logs their roads."),
           scene: Optional[Path] = typer.Option(None, help="openscenario, a folder of behaviour variants never "
                                                           "rendered (variants.json of `omniscs scs behavior`): the "
                                                           "scene store they were made from."),
           workspace: Optional[Path] = workspace_option()) -> None:
    """Export every variant store of a dataset as one nuScenes dataroot (with map expansion), for UniAD, or as one
    OpenSCENARIO scenario per variant on its scene's OpenDRIVE road network."""
    from omniscs.export import WRITERS, export_scenes

    if format not in ("nuscenes", "uniad", "openscenario") or format not in WRITERS:
        raise OmniscsError(f"unknown dataset export format {format!r}; use nuscenes, uniad or openscenario")
    if nuscenes_maps is not None and format != "openscenario":
        raise OmniscsError("--nuscenes-maps applies to --format openscenario only")
    if nuscenes_maps is not None and not (nuscenes_maps / "maps" / "expansion").is_dir():
        raise OmniscsError(f"--nuscenes-maps {nuscenes_maps} has no maps/expansion folder; name the nuScenes dataroot "
                           "the logs were read from")
    if scene is not None:
        if format != "openscenario" or not (Path(dataset) / "variants.json").is_file():
            raise OmniscsError("--scene applies to --format openscenario of a folder of behaviour variants "
                               "(variants.json) only")
        from omniscs.export.openscenario import export_behaviour_variants

        check_out(out, overwrite)
        export_behaviour_variants(Path(dataset) / "variants.json", scene, out, overwrite=overwrite,
                                  nuscenes_maps=nuscenes_maps)
        console.print(f"the behaviour variants of {dataset} exported as openscenario to {out}")
        return
    path, stores = variant_stores(dataset, workspace)
    check_out(out, overwrite)
    options = {"location": location, "keep_unseen": keep_unseen}
    if format == "uniad":
        options.update(box_convention=box_convention, val_scenes=tuple(val_scene))
    elif box_convention != "v1" or val_scene:
        raise OmniscsError("--box-convention and --val-scene apply to --format uniad only")
    if format == "openscenario":
        if location != "boston-seaport" or keep_unseen:
            raise OmniscsError("--location and --keep-unseen apply to --format nuscenes and uniad only")
        options = {"nuscenes_maps": nuscenes_maps}
    with progress_bars() as bars:
        export_scenes(stores, format, out, overwrite=overwrite, progress=bars.sink(f"export {format}"), **options)
    console.print(f"{len(stores)} variant store(s) of {path.name} exported as {format} to {out}")
