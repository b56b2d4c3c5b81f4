"""The ``omniscs`` command line: the top floor, which starts flows and runs quick domain tools."""
from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from omniscs.errors import OmniscsError

app = typer.Typer(help="OmniSCS data factory: safety-critical driving scenarios from ordinary logs.",
                  pretty_exceptions_enable=False, no_args_is_help=True)
world_app = typer.Typer(help="Procedural driving worlds (the embedded synthetic default input).", no_args_is_help=True)
scene_app = typer.Typer(help="Inspect scene stores.", no_args_is_help=True)
catalog_app = typer.Typer(help="Query the Parquet catalog with DuckDB.", no_args_is_help=True)
bench_app = typer.Typer(help="Benchmarks; results go to reports/.", no_args_is_help=True)
scs_app = typer.Typer(help="Safety-critical scenario synthesis (behaviour-level variants).", no_args_is_help=True)
app.add_typer(world_app, name="world")
app.add_typer(scs_app, name="scs")
app.add_typer(scene_app, name="scene")
app.add_typer(catalog_app, name="catalog")
app.add_typer(bench_app, name="bench")

console = Console(soft_wrap=True)  # paths and ids stay whole when output is not a terminal
err_console = Console(stderr=True)

#: Sources of the demo run: every road template, the parked-truck scene, and low-light variants.
DEMO_SOURCES = ("syn:straight_parked_truck:3:day", "syn:t_junction:1:dusk", "syn:intersection:2:day",
                "syn:straight:0:night")
DEMO_FRAMES = 20


def _progress() -> Progress:
    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                    TimeElapsedColumn(), TimeRemainingColumn(), console=err_console, transient=False)


def _print_table(rows: list[dict], title: str | None = None) -> None:
    table = Table(title=title)
    if not rows:
        console.print("(no rows)")
        return
    for col in rows[0]:
        table.add_column(str(col), overflow="fold")
    for row in rows:
        table.add_row(*[_fmt(v) for v in row.values()])
    console.print(table)


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


# ----------------------------------------------------------------------------- world
@world_app.command("make")
def world_make(
    out: Path = typer.Option(..., help="Directory to write the scene store to (must not exist)."),
    template: str = typer.Option("straight", help="Road layout template."),
    seed: int = typer.Option(0, help="Seed for layout, assets and traffic."),
    frames: int = typer.Option(40, help="Frames at 10 Hz."),
    cameras: int = typer.Option(3, help="Cameras, 1 to 6, nuScenes-like placement."),
    width: int = typer.Option(480), height: int = typer.Option(270),
    lighting: str = typer.Option("day", help="day, dusk, night or fog."),
    overwrite: bool = typer.Option(False, help="Replace an existing scene store at --out."),
) -> None:
    """Generate a procedural driving log and render it into a scene store with exact ground truth."""
    from omniscs.scene import SyntheticSource, load_scene
    from omniscs.scene.ingest import _check_synthetic
    from omniscs.scene.synthetic import write_synthetic_scene

    source = SyntheticSource(template, seed, lighting, frames, cameras, width, height)
    _check_synthetic(source)
    if out.exists() and not overwrite:
        raise OmniscsError(f"{out} already exists; choose another --out or pass --overwrite")
    started = time.perf_counter()
    with _progress() as bar:
        task = bar.add_task(f"render {source.scene_id()}", total=frames * (cameras + 1))
        write_synthetic_scene(source, out, overwrite=overwrite, progress=lambda d, t: bar.update(task, completed=d))
    scene = load_scene(out)
    console.print(f"wrote {scene} to {out} in {time.perf_counter() - started:.1f} s")


def _read_edits(edit: Optional[str]) -> list:
    """Edits from a JSON string, or from a file when the option starts with '@'."""
    from omniscs.edits import parse_edits

    if not edit:
        return []
    if edit.startswith("@"):
        path = Path(edit[1:])
        if not path.is_file():
            raise OmniscsError(f"edit file {path} does not exist")
        edit = path.read_text()
    return parse_edits(edit)


@world_app.command("render")
def world_render(
    scene_path: Path = typer.Argument(..., help="A synthetic scene store (it keeps the world it came from)."),
    out: Path = typer.Option(..., help="PNG to write."),
    camera: str = typer.Option("CAM_FRONT"), frame: int = typer.Option(0),
    edit: Optional[str] = typer.Option(None, help="Edit list as JSON, or @file.json (see README)."),
    masks: bool = typer.Option(False, help="Append the instance mask and depth beside the image."),
) -> None:
    """Ground truth for an edit: re-render a synthetic scene's world with edits applied."""
    import cv2
    import numpy as np

    from omniscs.preview import track_colour
    from omniscs.scene import load_scene
    from omniscs.storage import atomic_write_bytes
    from omniscs.world import WorldRenderer, apply_edits

    scene = load_scene(scene_path)
    if scene.world is None:
        raise OmniscsError(f"{scene_path} is not a synthetic scene (no world.json); only those can be re-rendered")
    world = apply_edits(scene.world, _read_edits(edit))
    scene.camera(camera)
    scene.check_frame(frame)
    r = WorldRenderer(world).render_camera(frame, camera)
    tiles = [r.rgb]
    if masks:
        ids = np.unique(r.instance[r.instance >= 0])
        inst = np.zeros_like(r.rgb)
        for tid in ids:
            inst[r.instance == tid] = track_colour(int(tid))
        far = float(np.percentile(r.depth[r.depth > 0], 95)) if np.any(r.depth > 0) else 1.0
        d = (255 * (1 - np.clip(r.depth / far, 0, 1))).astype(np.uint8)
        d[r.depth == 0] = 0
        tiles += [inst, cv2.applyColorMap(d, cv2.COLORMAP_TURBO)[..., ::-1]]
    ok, png = cv2.imencode(".png", cv2.cvtColor(np.concatenate(tiles, axis=1), cv2.COLOR_RGB2BGR))
    atomic_write_bytes(out, png.tobytes())
    console.print(f"wrote {out}")


@world_app.command("export")
def world_export(
    scenes: list[Path] = typer.Argument(..., help="Scene stores to export (one dataset holds them all)."),
    fmt: str = typer.Option(..., "--format", help="nuscenes, kitti or waymo-v2."),
    out: Path = typer.Option(..., help="Dataset root to write (must not exist)."),
    version: str = typer.Option("v1.0-trainval", help="nuScenes: table version folder."),
    keyframe_every: Optional[int] = typer.Option(None, help="nuScenes: frames per keyframe (default: 2 Hz)."),
    camera: str = typer.Option("CAM_FRONT", help="KITTI: the camera written as image_02."),
    overwrite: bool = typer.Option(False, help="Replace an existing dataset at --out."),
) -> None:
    """Write scene stores as a nuScenes v1.0, KITTI tracking or Waymo Open Dataset v2 dataset."""
    from omniscs.export import WRITERS, export_scenes

    if fmt not in WRITERS:
        raise OmniscsError(f"unknown --format {fmt!r}; use one of {list(WRITERS)}")
    options = {"nuscenes": {"version": version, "keyframe_every": keyframe_every}, "kitti": {"camera": camera},
               "waymo-v2": {}}[fmt]
    started = time.perf_counter()
    with _progress() as bar:
        task = bar.add_task(f"export {fmt}", total=None)
        export_scenes(scenes, fmt, out, overwrite=overwrite,
                      progress=lambda d, t: bar.update(task, completed=d, total=t), **options)
    console.print(f"wrote {len(scenes)} scene(s) as {fmt} to {out} in {time.perf_counter() - started:.1f} s")


# ----------------------------------------------------------------------------- ingest
@app.command("ingest")
def ingest_dataset_cmd(
    source: str = typer.Option(..., "--source", help="Dataset format: nuscenes, kitti or waymo-v2."),
    dataroot: Path = typer.Option(..., help="nuScenes root (holds v1.0-*/), KITTI tracking root, Waymo v2 split folder."),
    out: Path = typer.Option(..., help="Folder for the scene stores (one sub-folder per scene)."),
    scenes: Optional[list[str]] = typer.Option(None, "--scenes", help="Scenes / sequences / segments to read "
                                               "(repeat or comma-separate; default: all)."),
    version: Optional[str] = typer.Option(None, help="nuScenes table version (default: the only one); KITTI split."),
    sweeps: bool = typer.Option(False, help="nuScenes: every LiDAR sweep (annotations interpolated), not only keyframes."),
    cameras: Optional[str] = typer.Option(None, help="Comma-separated cameras to keep (default: all)."),
    skip_bad_frames: bool = typer.Option(False, "--skip-bad-frames",
                                         help="Leave unreadable frames out with a warning instead of failing."),
    overwrite: bool = typer.Option(False, help="Read scenes again even when an up-to-date store exists."),
) -> None:
    """Read scenes of a recorded dataset into validated scene stores."""
    import warnings

    from omniscs.scene import DatasetSource, ingest_dataset
    from omniscs.scene.sources import FORMATS, SkippedFramesWarning, list_scenes

    if source not in FORMATS:
        raise OmniscsError(f"unknown --source {source!r}; use one of {list(FORMATS)}")
    if not dataroot.is_dir():
        raise OmniscsError(f"--dataroot {dataroot} is not a directory")
    names = [n for item in (scenes or []) for n in item.split(",") if n] or list_scenes(source, dataroot, version)
    if not names:
        raise OmniscsError(f"{dataroot} holds no {source} scene")
    cams = tuple(c for c in cameras.split(",") if c) if cameras else None
    rows = []
    with _progress() as bar:
        for name in names:
            src = DatasetSource(source, str(dataroot.resolve()), name, version=version, cameras=cams, sweeps=sweeps,
                                skip_bad_frames=skip_bad_frames)
            task = bar.add_task(f"{source} {name}", total=None)
            started = time.perf_counter()
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", SkippedFramesWarning)
                result = ingest_dataset(src, out, overwrite=overwrite,
                                        progress=lambda d, t, task=task: bar.update(task, completed=d, total=t))
            for w in caught:
                err_console.print(f"[yellow]warning:[/] {w.message}", highlight=False, soft_wrap=True)
            from omniscs.scene import load_scene

            scene = load_scene(result.path)
            seconds = time.perf_counter() - started
            rows.append({"scene": name, "scene_id": scene.scene_id, "frames": scene.n_frames,
                         "boxes": len(scene.boxes), "skipped": len(scene.manifest.get("skipped_frames", [])),
                         "reused": result.reused, "seconds": seconds, "path": str(result.path)})
    _print_table(rows, title=f"{source} {dataroot}")


# ----------------------------------------------------------------------------- scene
@scene_app.command("info")
def scene_info(path: Path, as_json: bool = typer.Option(False, "--json", help="Print JSON.")) -> None:
    """Summarise a scene store: source, frames, cameras, tracks."""
    from omniscs.scene import load_scene
    from omniscs.scene.summary import agent_rows

    scene = load_scene(path)
    agents = agent_rows(scene)
    info = {
        "scene_id": scene.scene_id, "path": str(scene.path), "source": scene.source,
        "n_frames": scene.n_frames,
        "duration_s": float((scene.frames.timestamp_us.iloc[-1] - scene.frames.timestamp_us.iloc[0]) * 1e-6),
        "cameras": {c: {"size": list(scene.image_size(c))} for c in scene.camera_names},
        "has_lidar": scene.has_lidar, "has_gt": scene.has_gt, "content_hash": scene.content_hash,
        "n_tracks": len(agents), "n_moving": sum(a["moving"] for a in agents),
        "tracks": [{k: a[k] for k in ("track_id", "category", "n_frames", "path_length_m", "moving",
                                      "max_visible_pixels", "min_distance_to_ego_m")} for a in agents],
    }
    if as_json:
        typer.echo(json.dumps(info, indent=2, default=str))
        return
    console.print(f"[bold]{info['scene_id']}[/]  {info['path']}")
    console.print(f"source: {json.dumps(info['source'])}")
    console.print(f"{info['n_frames']} frames over {info['duration_s']:.1f} s; cameras: "
                  + ", ".join(f"{c} {v['size'][0]}x{v['size'][1]}" for c, v in info["cameras"].items()))
    console.print(f"LiDAR: {info['has_lidar']}; ground truth: {info['has_gt']}; "
                  f"{info['n_tracks']} tracks ({info['n_moving']} moving)")
    _print_table(info["tracks"], title="tracks")


@scene_app.command("preview")
def scene_preview(path: Path, out: Optional[Path] = typer.Option(None, help="Folder for the PNGs (default: PATH/preview).")) -> None:
    """Write a contact sheet (cameras over time, boxes projected) and a bird's-eye trajectory plot."""
    from omniscs.preview import write_previews
    from omniscs.scene import load_scene

    scene = load_scene(path)
    paths = write_previews(scene, out or Path(path) / "preview")
    for name, p in paths.items():
        console.print(f"{name}: {p}")


# ----------------------------------------------------------------------------- flows
def _run_generate(sources: list[str], workspace: Optional[Path], run_id: Optional[str], frames: int, cameras: int,
                  width: int, height: int, previews: bool) -> dict:
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    from omniscs.scene import parse_source
    for s in sources:  # fail on a bad source before starting the orchestrator
        parse_source(s)
    from flows.generate import generate_dataset

    return generate_dataset(sources=list(sources), workspace=str(workspace) if workspace else None, run_id=run_id,
                            n_frames=frames, n_cameras=cameras, width=width, height=height, previews=previews)


@app.command("generate")
def generate(
    sources: list[str] = typer.Argument(..., help="syn:TEMPLATE:SEED[:LIGHTING] or scene-store paths."),
    workspace: Optional[Path] = typer.Option(None, help="Workspace root (default $OMNISCS_HOME or ./omniscs-data)."),
    run_id: Optional[str] = typer.Option(None, help="Run id (default: time-stamped)."),
    frames: int = typer.Option(40), cameras: int = typer.Option(3),
    width: int = typer.Option(480), height: int = typer.Option(270),
    previews: bool = typer.Option(True, help="Write contact sheets and BEV plots."),
) -> None:
    """Run the generate_dataset flow over the given sources."""
    result = _run_generate(sources, workspace, run_id, frames, cameras, width, height, previews)
    console.print(f"run {result['run_id']}: {len(result['scenes'])} scene(s) in {result['workspace']}")


@app.command("demo")
def demo(workspace: Optional[Path] = typer.Option(None, help="Workspace root (default $OMNISCS_HOME or ./omniscs-data).")) -> None:
    """A small multi-scene run on the embedded synthetic world; prints where everything went."""
    from omniscs import catalog
    from omniscs.storage import workspace_root

    started = time.perf_counter()
    result = _run_generate(list(DEMO_SOURCES), workspace, None, DEMO_FRAMES, 3, 480, 270, True)
    ws = workspace_root(result["workspace"])
    root = catalog.catalog_root(ws)
    rows = catalog.query(root, f"""
        SELECT s.scene_id, s.n_frames, s.n_tracks, s.n_moving, s.reused,
               round(s.ingest_seconds, 1) AS ingest_s,
               (SELECT count(*) FROM agents a WHERE a.run_id = s.run_id AND a.scene_id = s.scene_id
                AND a.max_visible_pixels > 0) AS visible_tracks
        FROM scenes s WHERE s.run_id = '{result['run_id']}' ORDER BY s.scene_id""").to_pylist()
    _print_table(rows, title=f"run {result['run_id']}")
    console.print(f"scene stores: {ws / 'scenes'}")
    for s in result["scenes"]:
        console.print(f"  {s['path']}")
    console.print(f"previews:     {ws / 'previews'}")
    for p in result["previews"]:
        console.print(f"  {p}/contact_sheet.png  {p}/bev.png")
    console.print(f"catalog:      {root}  (try: omniscs catalog query \"SELECT category, count(*) FROM agents GROUP BY 1\""
                  + (f" --workspace {ws}" if workspace else "") + ")")
    console.print(f"demo finished in {time.perf_counter() - started:.1f} s")


# ----------------------------------------------------------------------------- catalog
@catalog_app.command("query")
def catalog_query(
    sql: str = typer.Argument(..., help="SQL over the views runs, scenes, agents, frames."),
    workspace: Optional[Path] = typer.Option(None, help="Workspace root (default $OMNISCS_HOME or ./omniscs-data)."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON rows."),
    as_csv: bool = typer.Option(False, "--csv", help="Print CSV."),
) -> None:
    """Run DuckDB SQL over the catalog and print the result."""
    from omniscs import catalog
    from omniscs.storage import workspace_root

    table = catalog.query(catalog.catalog_root(workspace_root(workspace)), sql)
    if as_json:
        typer.echo(json.dumps(table.to_pylist(), indent=2, default=str))
    elif as_csv:
        typer.echo(table.to_pandas().to_csv(index=False), nl=False)
    else:
        _print_table(table.to_pylist())


@catalog_app.command("views")
def catalog_views(workspace: Optional[Path] = typer.Option(None)) -> None:
    """Print DuckDB statements that create the catalog views (for the duckdb shell)."""
    from omniscs import catalog
    from omniscs.storage import workspace_root

    typer.echo(catalog.views_sql(str(catalog.catalog_root(workspace_root(workspace)))), nl=False)


# ----------------------------------------------------------------------------- scs
@scs_app.command("train-behavior")
def scs_train_behavior(
    out: Path = typer.Option(..., help="Checkpoint folder to write (must not exist unless --overwrite)."),
    preset: str = typer.Option("balanced", help="fast (smoke test), balanced (the shipped checkpoint) or accurate."),
    seed: int = typer.Option(0, help="Seed of training worlds, held-out worlds and initialisation."),
    worlds: Optional[int] = typer.Option(None, help="Procedural training worlds (default: the preset's)."),
    steps: Optional[int] = typer.Option(None, help="Optimiser steps (default: the preset's)."),
    scene: Optional[list[Path]] = typer.Option(None, "--scene", help="Scene stores to add as training data (repeat)."),
    threads: int = typer.Option(1, help="torch CPU threads."),
    overwrite: bool = typer.Option(False, help="Replace an existing checkpoint at --out."),
) -> None:
    """Train the behaviour (traffic) model on procedural traffic (+ scene stores); writes weights, config and
    training.json (seed, command, held-out ADE/FDE against constant velocity)."""
    from omniscs.scs.behavior.train import train_model, train_preset

    overrides = {"seed": seed, "torch_threads": threads}
    if worlds is not None:
        overrides["n_worlds"] = worlds
    if steps is not None:
        overrides["steps"] = steps
    config = train_preset(preset, **overrides)
    if out.exists() and not overwrite:
        raise OmniscsError(f"{out} already exists; choose another --out or pass --overwrite")
    for p in scene or []:
        if not p.is_dir():
            raise OmniscsError(f"--scene {p} is not a scene-store directory")
    command = "omniscs " + " ".join(sys.argv[1:]) if sys.argv and "omniscs" in sys.argv[0] else ""
    with _progress() as bar:
        tasks: dict[str, int] = {}

        def progress(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = bar.add_task(stage, total=total)
            bar.update(tasks[stage], completed=done)

        _, record = train_model(config, out, command=command or f"omniscs scs train-behavior --out {out} "
                                f"--preset {preset} --seed {seed}", extra_scenes=list(scene or []),
                                progress=progress, overwrite=overwrite)
    rows = []
    for group in ("all", "moving"):
        m = record["heldout_metrics"][group]
        for name in ("posterior", "prior_mean", f"prior_min_of_{config.prior_samples}", "constant_velocity"):
            rows.append({"agents": f"{group} ({m['agents']})", "method": name, "ADE m": m[name]["ade"],
                         "FDE m": m[name]["fde"]})
    _print_table(rows, title=f"held-out ADE/FDE over {record['heldout_metrics']['horizon_s']:.1f} s")
    console.print(f"wrote {out} ({record['seconds']['training']:.0f} s training)")


@scs_app.command("behavior")
def scs_behavior(
    scene: str = typer.Argument(..., help="A scene store, or syn:TEMPLATE:SEED[:FRAMES] (procedural log, not rendered)."),
    variants: int = typer.Option(3, "--variants", help="How many variants (distinct adversaries, then time windows)."),
    out: Path = typer.Option(..., help="Folder for variants.json and one BEV PNG per variant."),
    checkpoint: Optional[Path] = typer.Option(None, help="Traffic-model checkpoint folder (default: the shipped one)."),
    preset: str = typer.Option("balanced", help="fast, balanced or accurate (optimisation steps)."),
    planner: str = typer.Option("replay", help="Ego plan: replay (the logged future) or rule (reacts, brakes)."),
    threads: int = typer.Option(1, help="torch CPU threads."),
    nsg: Optional[Path] = typer.Option(None, help="The scene's fitted scene graph (omniscs fit --behavior-variants "
                                                  "N): adds L_app, rendered by it."),
    app_frames: int = typer.Option(3, help="L_app: horizon steps rendered per optimisation step."),
    app_downscale: int = typer.Option(4, help="L_app: render at 1/N of the camera resolution."),
) -> None:
    """Behaviour-level SCS: perturb agents' latents so one of them collides with the ego plan, plausibly."""
    from omniscs.scs.behavior import PlannerConfig, adversarial_preset, load_traffic, write_scene_variants
    from omniscs.scs.behavior.planner import check_planner

    if variants < 1:
        raise OmniscsError(f"--variants must be at least 1; got {variants}")
    from omniscs.scs.behavior.adversarial import now_and_horizon
    from omniscs.scs.behavior.checkpoint import load_checkpoint

    config = adversarial_preset(preset, planner=PlannerConfig(kind=check_planner(planner)), torch_threads=threads)
    traffic = load_traffic(scene)
    now_and_horizon(traffic, load_checkpoint(checkpoint).config, config)  # user errors before any progress bar
    appearance = None
    if nsg is not None:
        from omniscs.scene import load_scene
        from omniscs.scs.behavior.scene_render import AppearanceRenderConfig, appearance_from_checkpoint

        if scene.startswith("syn:"):
            raise OmniscsError("--nsg needs a rendered scene store (a syn: log has no images to fit a graph to)")
        appearance = appearance_from_checkpoint(nsg, load_scene(Path(scene)), traffic, checkpoint, config,
                                                AppearanceRenderConfig(frames=app_frames, downscale=app_downscale))
    with _progress() as bar:
        task = bar.add_task(f"variants of {traffic.scene_id}", total=variants)
        result = write_scene_variants(traffic, out, variants, checkpoint, config, appearance, reuse=False,
                                      progress=lambda d, t: bar.update(task, completed=d))
    if not result.rows:
        raise OmniscsError(f"scene {traffic.scene_id} has no vehicle besides the ego at the now step; "
                           "no behaviour variant can be made")
    _print_table([{"variant": r["variant_id"], "kind": r["kind"], "hit": r["success"], "plausible": r["plausible"],
                   "t (s)": r["collision_time_s"], "L_beh": r["loss_beh"], "L_app": r["loss_app"],
                   "L_restore": r["loss_restore"],
                   "s": r["optimisation_seconds"]} for r in result.rows], title=str(result.variants_json))
    if appearance is None:
        console.print("L_app: off (give --nsg with the scene's fitted scene graph to add it)")
    for r in result.rows:
        for v in json.loads(result.variants_json.read_text()):
            if v["variant_id"] == r["variant_id"] and v["violations"]:
                console.print(f"{r['variant_id']}: " + "; ".join(v["violations"][:4]))
    console.print(f"wrote {result.variants_json} and {len(result.bev_pngs)} BEV picture(s)")


# ----------------------------------------------------------------------------- benchmarks
@bench_app.command("world")
def bench_world(
    seeds: str = typer.Option("0", help="Comma-separated seeds."),
    out: Path = typer.Option(Path("reports"), help="Folder for world_render.json/.md."),
    frames: int = typer.Option(40), cameras: int = typer.Option(3),
) -> None:
    """Time rendering a 40-frame, 3-camera 480x270 scene with LiDAR."""
    from omniscs.world.bench import run_world_benchmark

    result = run_world_benchmark(out, seeds=tuple(int(s) for s in seeds.split(",")), n_frames=frames,
                                 n_cameras=cameras)
    console.print((out / "world_render.md").read_text())
    console.print(f"wrote {out / 'world_render.json'}")
    del result


@bench_app.command("sources")
def bench_sources(
    out: Path = typer.Option(Path("reports"), help="Folder for sources_ingest.json/.md."),
    frames: int = typer.Option(10), cameras: int = typer.Option(6), repeats: int = typer.Option(3),
) -> None:
    """Time reading a 480x270 synthetic log back from nuScenes, KITTI and Waymo v2 (ms per frame)."""
    from omniscs.scene.sources.bench import run_sources_benchmark

    run_sources_benchmark(out, n_frames=frames, n_cameras=cameras, repeats=repeats)
    console.print((out / "sources_ingest.md").read_text())
    console.print(f"wrote {out / 'sources_ingest.json'}")


@bench_app.command("behavior")
def bench_behavior(
    out: Path = typer.Option(Path("reports"), help="Folder for behavior_bench.json/.md/.png."),
    scenes_per_template: int = typer.Option(5, help="Procedural scenes per road template."),
    variants: int = typer.Option(2, help="Variants per scene."),
    preset: str = typer.Option("balanced", help="Adversarial preset: fast, balanced or accurate."),
    checkpoint: Optional[Path] = typer.Option(None, help="Traffic-model checkpoint (default: the shipped one)."),
    rule_planner: bool = typer.Option(True, help="Also run against the reacting rule-based planner."),
    threads: int = typer.Option(1, help="torch CPU threads."),
    appearance_scenes: int = typer.Option(4, help="Rendered scenes fitted with a scene graph for the with/without "
                                                  "L_app comparison (0 skips it)."),
    workspace: Optional[Path] = typer.Option(None, help="Where those scenes and scene graphs go (and are reused)."),
    app_weights: str = typer.Option("1,30", help="Comma-separated L_app weights compared."),
    only_appearance: bool = typer.Option(False, help="Rerun only the L_app comparison in an existing report in --out."),
    seed_offset: int = typer.Option(2000, help="First scene seed: 2000 is the fixed set, any other a fresh one."),
    only_default: bool = typer.Option(False, help="Run only the default configuration on the procedural logs."),
    search_starts: int = typer.Option(192, help="Feasibility search: random starts per candidate adversary."),
) -> None:
    """Adversarial success, plausibility violations, accelerations and time per variant, with and without the
    plausibility penalty, with and without L_app (and its appearance drift), plus the traffic model's ADE/FDE."""
    from omniscs.scs.behavior.bench import BenchConfig, rerun_appearance_study, run_behavior_benchmark
    from omniscs.scs.behavior.feasibility import FeasibilityConfig
    from omniscs.scs.behavior.adversarial import adversarial_preset

    adversarial_preset(preset)
    try:
        weights = tuple(float(w) for w in app_weights.split(","))
    except ValueError:
        weights = ()
    if search_starts < 1:
        raise OmniscsError(f"--search-starts must be at least 1; got {search_starts}")
    if not weights or min(weights) <= 0:
        raise OmniscsError(f"--app-weights takes positive numbers like 1,30; got {app_weights!r}")
    config = BenchConfig(scenes_per_template=scenes_per_template, variants_per_scene=variants, preset=preset,
                         rule_planner=rule_planner, torch_threads=threads,
                         appearance_scenes=max(0, appearance_scenes), app_weights=weights,
                         seed_offset=seed_offset, only_default=only_default,
                         feasibility=FeasibilityConfig(starts=search_starts))
    if only_appearance:
        rerun_appearance_study(out, config, checkpoint, workspace)
        console.print((out / "behavior_bench.md").read_text())
        return
    with _progress() as bar:
        task = bar.add_task("behaviour variants", total=None)
        run_behavior_benchmark(out, config, checkpoint, progress=lambda d, t: bar.update(task, completed=d, total=t),
                               workspace=workspace)
    console.print((out / "behavior_bench.md").read_text())
    console.print(f"wrote {out / 'behavior_bench.json'}")


# ----------------------------------------------------------------------------- scene graph
def _fit_progress() -> Progress:
    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                    TextColumn("loss {task.fields[loss]:.4f}  PSNR {task.fields[psnr]:.2f} dB"), TimeElapsedColumn(),
                    TimeRemainingColumn(), console=err_console, transient=False)


def _seeds(text: str) -> tuple[int, ...]:
    try:
        seeds = tuple(int(s) for s in text.split(",") if s.strip())
    except ValueError:
        raise OmniscsError(f"--seeds must be comma-separated integers, e.g. 0,1,2; got {text!r}") from None
    if not seeds:
        raise OmniscsError("--seeds needs at least one seed")
    return seeds


@app.command("fit")
def fit_cmd(
    scene_path: Path = typer.Argument(..., help="A scene store (see omniscs world make / ingest)."),
    out: Path = typer.Option(..., help="Checkpoint folder to write (must not exist unless --overwrite)."),
    preset: str = typer.Option("balanced", help="fast, balanced or accurate."),
    iterations: Optional[int] = typer.Option(None, help="Override the preset's optimiser steps."),
    edit: Optional[str] = typer.Option(None, help="Edits the graph must support (their tracks become nodes): JSON or @file."),
    threads: int = typer.Option(1, help="torch CPU threads."),
    overwrite: bool = typer.Option(False, help="Replace an existing checkpoint at --out."),
    behavior_variants: int = typer.Option(0, help="Behaviour variants will be made with this graph (L_app): "
                                                  "every vehicle becomes a node."),
) -> None:
    """Fit a Gaussian scene graph (background, agent nodes, sky) to a scene store and save a checkpoint."""
    from omniscs.nsg import fit_preset, fit_scene
    from omniscs.plan import make_plan
    from omniscs.scene import load_scene

    if not scene_path.is_dir():
        raise OmniscsError(f"{scene_path} is not a scene-store directory")
    overrides = {"torch_threads": threads}
    if iterations is not None:
        if iterations < 1:
            raise OmniscsError(f"--iterations must be at least 1; got {iterations}")
        overrides["iterations"] = iterations
    config = fit_preset(preset, **overrides)
    if out.exists() and not overwrite:
        raise OmniscsError(f"{out} already exists; choose another --out or pass --overwrite")
    scene = load_scene(scene_path)
    plan = make_plan(scene, _read_edits(edit), config.plan, behavior_variants=behavior_variants)
    console.print(f"plan: {plan.summary()}")
    with _fit_progress() as bar:
        task = bar.add_task(f"fit {scene.scene_id} ({preset})", total=config.iterations, loss=float("nan"),
                            psnr=float("nan"))
        result = fit_scene(scene, config, plan, checkpoint_dir=out, overwrite=overwrite,
                           progress=lambda d, t, loss, p: bar.update(task, completed=d, loss=loss, psnr=p))
    m = result.metrics
    _print_table([{"Gaussians": m["n_gaussians"], "agent nodes": m["n_agent_nodes"], "fit s": m["fit_seconds"],
                   "train PSNR": m["train_psnr"], "held-out PSNR": m["heldout_psnr"], "held-out SSIM": m["heldout_ssim"],
                   "held-out views": m["heldout_views"]}], title=f"{scene.scene_id} ({preset})")
    console.print(f"wrote {out} (plan.json, graph.json, gaussians.safetensors, metrics.json)")


@app.command("render")
def render_cmd(
    checkpoint: Path = typer.Argument(..., help="A scene-graph checkpoint folder (omniscs fit --out)."),
    out: Path = typer.Option(..., help="PNG to write."),
    camera: str = typer.Option("CAM_FRONT"), frame: int = typer.Option(0),
    edit: Optional[str] = typer.Option(None, help="Edit list as JSON, or @file.json (see README)."),
    ego_pose: Optional[str] = typer.Option(None, help="Render from another ego pose: 'x,y,z,yaw' (world frame, m, rad)."),
    depth: bool = typer.Option(False, help="Append the expected depth beside the image."),
) -> None:
    """Render a fitted (optionally edited) scene graph from a logged camera, at a logged or any ego pose."""
    import numpy as np

    from omniscs.geometry import pose_from_xyz_yaw
    from omniscs.nsg.checkpoint import load_checkpoint
    from omniscs.nsg.edit import apply_graph_edits
    from omniscs.storage import atomic_write_with

    graph = load_checkpoint(checkpoint)
    edits = _read_edits(edit)
    if edits:
        graph = apply_graph_edits(graph, edits)
    world_from_ego = None
    if ego_pose is not None:
        try:
            values = [float(v) for v in ego_pose.split(",")]
        except ValueError:
            values = []
        if len(values) != 4 or not np.all(np.isfinite(values)):
            raise OmniscsError(f"--ego-pose must be four numbers x,y,z,yaw; got {ego_pose!r}")
        world_from_ego = pose_from_xyz_yaw(*values)
    result = graph.render(graph.view(camera, frame, world_from_ego))
    image = (result.rgb.clamp(0, 1).numpy() * 255).round().astype(np.uint8)
    if depth:
        d = result.depth.numpy()
        scale = float(np.percentile(d[d > 0], 95)) if np.any(d > 0) else 1.0
        grey = (np.clip(d / scale, 0, 1) * 255).astype(np.uint8)
        image = np.concatenate([image, np.repeat(grey[..., None], 3, -1)], 1)
    if out.suffix.lower() != ".png":
        raise OmniscsError(f"--out must end in .png; got {out}")
    from PIL import Image

    atomic_write_with(out, lambda buf: Image.fromarray(image).save(buf, format="PNG"))
    console.print(f"wrote {out} ({graph.scene_id}, {camera}, frame {frame}, {len(edits)} edit(s))")


@bench_app.command("fit")
def bench_fit(
    out: Path = typer.Option(Path("reports"), help="Folder for fit_bench.json/.md/.png."),
    seeds: str = typer.Option("0", help="Comma-separated seeds of the procedural scenes."),
    presets: str = typer.Option("fast,balanced,accurate", help="Comma-separated presets."),
    template: str = typer.Option("straight"), frames: int = typer.Option(40), cameras: int = typer.Option(3),
    width: int = typer.Option(480), height: int = typer.Option(270),
    workspace: Optional[Path] = typer.Option(None, help="Where the benchmark scenes are rendered (and reused)."),
) -> None:
    """Fit the same scenes with each preset: wall time, Gaussians and held-out PSNR/SSIM; a time-vs-PSNR plot."""
    from omniscs.nsg.bench import BenchScenes, run_fit_benchmark
    from omniscs.nsg.config import PRESETS

    chosen = tuple(p.strip() for p in presets.split(",") if p.strip())
    unknown = [p for p in chosen if p not in PRESETS]
    if unknown or not chosen:
        raise OmniscsError(f"unknown preset(s) {unknown}; use some of {list(PRESETS)}")
    scenes = BenchScenes(_seeds(seeds), template, "day", frames, cameras, width, height)
    with _progress() as bar:
        task = bar.add_task("bench fit", total=None)
        run_fit_benchmark(out, scenes, chosen, workspace,
                          progress=lambda msg: bar.update(task, description=msg))
    console.print((out / "fit_bench.md").read_text())
    console.print(f"wrote {out / 'fit_bench.json'} and {out / 'fit_bench.png'}")


@bench_app.command("edits")
def bench_edits(
    out: Path = typer.Option(Path("reports"), help="Folder for edits_bench.json/.md/.png."),
    seeds: str = typer.Option("0", help="Comma-separated seeds of the procedural scenes."),
    preset: str = typer.Option("balanced", help="Fit preset of the scene graphs."),
    agents: int = typer.Option(2, help="Edited agents per scene (the most visible ones)."),
    views: int = typer.Option(4, help="Evaluated views per agent and edit."),
    template: str = typer.Option("straight"), frames: int = typer.Option(40), cameras: int = typer.Option(3),
    width: int = typer.Option(480), height: int = typer.Option(270),
    workspace: Optional[Path] = typer.Option(None, help="Where the benchmark scenes are rendered (and reused)."),
) -> None:
    """Edit fidelity against ground truth: translate 2.0/3.5 m, rotate 90/180/270°; PSNR/SSIM full and masked."""
    from omniscs.nsg.bench import BenchScenes, run_edit_benchmark
    from omniscs.nsg.config import fit_preset

    fit_preset(preset)
    if agents < 1 or views < 1:
        raise OmniscsError("--agents and --views must be at least 1")
    scenes = BenchScenes(_seeds(seeds), template, "day", frames, cameras, width, height)
    with _progress() as bar:
        task = bar.add_task("bench edits", total=None)
        run_edit_benchmark(out, scenes, preset, agents, views, workspace=workspace,
                           progress=lambda msg: bar.update(task, description=msg))
    console.print((out / "edits_bench.md").read_text())
    console.print(f"wrote {out / 'edits_bench.json'} and {out / 'edits_bench.png'}")


@bench_app.command("render")
def bench_render(
    out: Path = typer.Option(Path("reports"), help="Folder for render_bench.json/.md/.png."),
    resolutions: str = typer.Option("320x180,640x360,1280x720", help="Comma-separated WxH."),
    counts: str = typer.Option("10000,100000,1000000", help="Comma-separated Gaussian counts."),
    repeats: int = typer.Option(5, help="Timed repeats per cell (median reported)."),
    reference_budget_s: float = typer.Option(60.0, help="Skip reference cells expected to take longer."),
) -> None:
    """Time the Gaussian rasterizer (forward, forward+backward) per backend; cpu/reference speed-up."""
    from omniscs.render.bench import run_render_benchmark

    try:
        sizes = tuple(tuple(int(v) for v in r.lower().split("x")) for r in resolutions.split(","))
        ns = tuple(int(c) for c in counts.split(","))
    except ValueError:
        sizes, ns = (), ()
    if not sizes or any(len(s) != 2 or min(s) < 1 for s in sizes) or not ns or min(ns) < 1:
        raise OmniscsError("--resolutions is like 640x360,1280x720 and --counts like 10000,100000")
    run_render_benchmark(out, resolutions=sizes, counts=ns, repeats=repeats, reference_budget_s=reference_budget_s)
    console.print((out / "render_bench.md").read_text())
    console.print(f"wrote {out / 'render_bench.json'}")


def main() -> None:
    try:
        app()
    except OmniscsError as exc:
        err_console.print(f"[red]error:[/] {exc}", highlight=False, soft_wrap=True)
        sys.exit(2)


if __name__ == "__main__":
    main()
