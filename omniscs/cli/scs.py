"""``omniscs scs``: behaviour-level safety-critical scenario synthesis (train the traffic model, make variants)."""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer

from omniscs.checks import MAX_SEED, MAX_THREADS

from omniscs.cli.common import check_out, console, print_error, print_table, progress_bars, read_edits
from omniscs.errors import OmniscsError
from omniscs.untrusted import read_own_json

app = typer.Typer(help="Safety-critical scenario synthesis (behaviour-level variants).", no_args_is_help=True)


@app.command("train-behavior")
def scs_train_behavior(
    out: Path = typer.Option(..., help="Checkpoint folder to write (must not exist unless --overwrite)."),
    preset: str = typer.Option("balanced", help="fast (smoke test), balanced (the shipped checkpoint) or accurate."),
    seed: int = typer.Option(0, min=0, max=MAX_SEED,
                             help="Seed of training worlds, held-out worlds and initialisation."),
    worlds: Optional[int] = typer.Option(None, help="Procedural training worlds (default: the preset's)."),
    steps: Optional[int] = typer.Option(None, help="Optimiser steps (default: the preset's)."),
    scene: Optional[list[Path]] = typer.Option(None, "--scene", help="Scene stores to add as training data (repeat)."),
    threads: int = typer.Option(1, min=1, max=MAX_THREADS, help="torch CPU threads."),
    overwrite: bool = typer.Option(False, help="Replace an existing checkpoint at --out."),
) -> None:
    """Train the behaviour (traffic) model on procedural traffic (+ scene stores); writes weights, config and
    training.json (seed, command, held-out ADE/FDE against constant velocity)."""
    from omniscs.pipeline.procedural import procedural_traffic
    from omniscs.scs.behavior.train import train_model, train_preset

    overrides = {"seed": seed, "torch_threads": threads}
    if worlds is not None:
        overrides["n_worlds"] = worlds
    if steps is not None:
        overrides["steps"] = steps
    config = train_preset(preset, **overrides)
    check_out(out, overwrite)
    for p in scene or []:
        if not p.is_dir():
            raise OmniscsError(f"--scene {p} is not a scene-store directory")
    command = "omniscs " + " ".join(sys.argv[1:]) if sys.argv and "omniscs" in sys.argv[0] else ""
    with progress_bars() as bars:
        def progress(stage: str, done: int, total: int) -> None:
            bars.sink(stage)(done, total)

        _, record = train_model(config, procedural_traffic, out,
                                command=command or f"omniscs scs train-behavior --out {out} --preset {preset} "
                                f"--seed {seed}", extra_scenes=list(scene or []), progress=progress,
                                overwrite=overwrite)
    rows = []
    for group in ("all", "moving"):
        m = record["heldout_metrics"][group]
        for name in ("posterior", "prior_mean", f"prior_min_of_{config.prior_samples}", "constant_velocity"):
            rows.append({"agents": f"{group} ({m['agents']})", "method": name, "ADE m": m[name]["ade"],
                         "FDE m": m[name]["fde"]})
    print_table(rows, title=f"held-out ADE/FDE over {record['heldout_metrics']['horizon_s']:.1f} s")
    console.print(f"wrote {out} ({record['seconds']['training']:.0f} s training)")


@app.command("behavior")
def scs_behavior(
    scene: str = typer.Argument(..., help="A scene store, or syn:TEMPLATE:SEED[:LIGHTING] (a procedural log, "
                                          "not rendered)."),
    frames: int = typer.Option(40, help="Frames of a syn: log (10 Hz; a scene store keeps its own)."),
    variants: int = typer.Option(3, "--variants", help="How many variants (distinct adversaries, then time windows)."),
    out: Path = typer.Option(..., help="Folder for variants.json and one BEV PNG per variant."),
    checkpoint: Optional[Path] = typer.Option(None, help="Traffic-model checkpoint folder (default: the shipped one)."),
    preset: str = typer.Option("balanced", help="fast, balanced or accurate (optimisation steps)."),
    planner: str = typer.Option("replay", help="Ego plan: replay (the logged future) or rule (reacts, brakes)."),
    threads: int = typer.Option(1, min=1, max=MAX_THREADS, help="torch CPU threads."),
    nsg: Optional[Path] = typer.Option(None, help="The scene's fitted scene graph (omniscs fit --behavior-variants "
                                                  "N): adds L_app, rendered by it."),
    app_frames: int = typer.Option(3, help="L_app: horizon steps rendered per optimisation step."),
    app_downscale: int = typer.Option(4, help="L_app: render at 1/N of the camera resolution."),
) -> None:
    """Behaviour-level SCS: perturb agents' latents so one of them collides with the ego plan, plausibly."""
    from omniscs.pipeline.procedural import traffic_for_source
    from omniscs.scene import SyntheticSource, parse_source
    from omniscs.scs.behavior import PlannerConfig, adversarial_preset, now_and_horizon, write_scene_variants
    from omniscs.scs.behavior.checkpoint import load_traffic_model
    from omniscs.scs.behavior.planner import check_planner

    # the options first (cheap), then the scene and the checkpoint
    if variants < 1:
        raise OmniscsError(f"--variants must be at least 1; got {variants}")
    config = adversarial_preset(preset, planner=PlannerConfig(kind=check_planner(planner)), torch_threads=threads)
    for name, value in (("--app-frames", app_frames), ("--app-downscale", app_downscale)):
        if value < 1:
            raise OmniscsError(f"{name} must be at least 1; got {value}")
    if nsg is not None and not (nsg / "graph.json").is_file():
        raise OmniscsError(f"--nsg {nsg} is not a scene-graph checkpoint (no graph.json); fit one with omniscs fit")
    check_out(out, overwrite=True)  # variants.json and the pictures go into --out (an existing folder is fine)
    source = parse_source(scene, n_frames=frames)
    traffic = traffic_for_source(source)
    now_and_horizon(traffic, load_traffic_model(checkpoint).config, config)  # user errors before any progress bar
    consistency = None
    if nsg is not None:
        from omniscs.scene import load_scene
        from omniscs.scs.behavior.scene_render import RenderConsistencyConfig, render_consistency_from_checkpoint

        if isinstance(source, SyntheticSource):
            raise OmniscsError("--nsg needs a rendered scene store (a syn: log has no images to fit a graph to)")
        consistency = render_consistency_from_checkpoint(nsg, load_scene(Path(scene)), traffic, checkpoint, config,
                                                         RenderConsistencyConfig(frames=app_frames,
                                                                                 downscale=app_downscale))
    with progress_bars() as bars:
        result = write_scene_variants(traffic, out, variants, checkpoint, config, consistency,
                                      progress=bars.sink(f"{traffic.scene_id} behavior"))
    if not result.rows:
        raise OmniscsError(f"scene {traffic.scene_id} has no vehicle besides the ego at the now step; "
                           "no behaviour variant can be made")
    print_table([{"variant": r["variant_id"], "kind": r["kind"], "hit": r["success"], "plausible": r["plausible"],
                   "t (s)": r["collision_time_s"], "L_beh": r["loss_beh"], "L_app": r["loss_app"],
                   "L_restore": r["loss_restore"],
                   "s": r["optimisation_seconds"]} for r in result.rows], title=str(result.variants_json))
    if consistency is None:
        console.print("L_app: off (give --nsg with the scene's fitted scene graph to add it)")
    for r in result.rows:
        for v in read_own_json(result.variants_json, "run the command again", expect=list):
            if v["variant_id"] == r["variant_id"] and v["violations"]:
                console.print(f"{r['variant_id']}: " + "; ".join(v["violations"][:4]))
    console.print(f"wrote {result.variants_json} and {len(result.bev_pngs)} BEV picture(s)")


@app.command("appearance")
def scs_appearance(
    scene: Path = typer.Argument(..., help="A scene store (its fitted scene graph: --nsg, else the newest one of the "
                                           "workspace)."),
    out: Path = typer.Option(..., help="Folder for variants.json, one annotated scene store per variant (scenes/), "
                                       "rows.json and preview.png."),
    pool: Optional[Path] = typer.Option(None, help="Model pool the objects come from (pm-... ids)."),
    nsg: Optional[Path] = typer.Option(None, help="The scene's fitted scene graph (default: its newest checkpoint in "
                                                  "the workspace)."),
    insert: Optional[str] = typer.Option(None, help="Insert this model (pm-... or nsg:TRACK[@CKPT]) at --pose."),
    pose: Optional[str] = typer.Option(None, help="x,y,yaw[,roll,pitch] of --insert: world metres, degrees (roll 180 "
                                                  "= overturned, 90 = on its side); it rests on the road."),
    replace: Optional[int] = typer.Option(None, help="Replace this track's model (it keeps its motion) ..."),
    with_model: Optional[str] = typer.Option(None, "--with", help="... by this model (its own size)."),
    sample: Optional[int] = typer.Option(None, help="Draw N variants (1-to-N): objects replace vehicles or stand at "
                                                    "sampled valid poses, upright, on the side and overturned in turn."),
    object_ids: Optional[list[str]] = typer.Option(None, "--object", help="--sample: objects to use (repeat; "
                                                                          "default: every model of --pool)."),
    camera: Optional[str] = typer.Option(None, help="--sample: the camera objects must be seen by."),
    distance: str = typer.Option("8,30", help="--sample: lo,hi metres from that camera."),
    seed: int = typer.Option(0, min=0, max=MAX_SEED, help="--sample: seed."),
    colour: bool = typer.Option(True, "--colour/--no-colour", help="Map objects' colours by the scene's colour "
                                                                   "transform (estimated from its vehicles)."),
    shadow: bool = typer.Option(True, "--shadow/--no-shadow", help="A soft contact shadow under each object."),
    edit: Optional[str] = typer.Option(None, help="A designed scenario instead: an edit spec (JSON or @file, e.g. "
                                                  "saved by omniscs view) rendered as one variant d000 (models from "
                                                  "--pool)."),
    overwrite: bool = typer.Option(False, help="Replace an existing --out written by omniscs."),
) -> None:
    """Appearance-level SCS: composite pool objects into a fitted scene (replace an agent's model, insert at a pose,
    sample N valid placements, or render an edit spec as one designed variant) and render them with automatic
    ground truth."""
    from omniscs.pipeline.appearance import appearance_scene_set

    check_out(out, overwrite)
    with progress_bars() as bars:
        result = appearance_scene_set(scene, out, pool=pool, checkpoint=nsg, insert=insert, pose=pose,
                                      replace=replace, with_model=with_model, sample=sample,
                                      objects=tuple(object_ids or ()), camera=camera, distance=distance, seed=seed,
                                      colour=colour, shadow=shadow, edits=read_edits(edit),
                                      progress=bars.sink(f"{scene.name} appearance"))
    print_table([{"variant": v["variant_id"], "placement": v.get("placement", v["kind"]), "object": v["object_id"],
                  "track": v.get("track_id", v.get("adversary")),
                  "pose": (v.get("pose") or {}).get("name", "user") if v.get("placement") == "insert"
                  else "its motion" if v.get("placement") == "replace" else f"{len(v['edits'])} edit(s)"}
                 for v in result["specs"]], title=str(out / "variants.json"))
    print_table([{"variant": s["variant_id"], "frames": s["n_frames"], "images": s["n_images"],
                  "boxes": s["n_annotations"], "PSNR dB": s["fidelity_psnr"], "object PSNR dB":
                  s["fidelity_masked_psnr"]} for s in result["variants"]], title="rendered and annotated")
    console.print(f"wrote {out} ({result['n_images']} images, {result['n_annotations']} box annotations); "
                  f"preview: {out / 'preview.png'}")
    if result.get("unrepaired"):
        print_error(f"track(s) {', '.join(map(str, result['unrepaired']))}: the variant uncovers the footprint of a "
                    "large static object, and the background it hid is not repaired here, so a ghost of it shows; "
                    "`omniscs generate` with --appearance-object (or --edit) repairs it first (its uncovered "
                    "stage)", label="warning", style="yellow")


@app.command("mine")
def scs_mine(
    results: Path = typer.Option(..., help="Detection results in the nuScenes results format (JSON)."),
    dataset: Path = typer.Option(..., help="A nuScenes dataroot (e.g. an OmniSCS export: omniscs dataset export)."),
    version: Optional[str] = typer.Option(None, help="The dataroot's version folder (default: the only one there; "
                                                     "the factory's exports write v1.0-trainval)."),
    out: Path = typer.Option(..., help="Folder for missed.json, missed.md and missed.png."),
    match_distance: float = typer.Option(2.0, help="Centre distance (m) under which a detection matches."),
    min_score: float = typer.Option(0.0, help="Detections below this score are ignored."),
    overwrite: bool = typer.Option(False, help="Replace an existing --out written by omniscs."),
    models_into: Optional[Path] = typer.Option(None, "--models-into", help="Also make a pool model of each picked "
                                               "missed object traced to a fitted scene of --workspace (its track's "
                                               "node, mirror-completed) in this pool; prints their ids "
                                               "(for --appearance-object)."),
    workspace: Optional[Path] = typer.Option(None, help="With --models-into: the workspace whose scenes the dataroot "
                                                        "was exported from."),
) -> None:
    """What a detector misses: ground-truth boxes no detection matches (nuScenes' centre-distance rule), by category,
    distance, visibility, orientation and pose, and the objects worth compositing (appearance-level SCS)."""
    from omniscs.eval.mining import MiningConfig, mine, pick_scs_objects

    check_out(out, overwrite)
    report = mine(dataset, version, results, out, MiningConfig(match_distance_m=match_distance, min_score=min_score),
                  overwrite=overwrite)
    print_table([{k: r[k] for k in r} for r in report.by_category.to_dict("records")], title="missed by category")
    picks = pick_scs_objects(report)
    print_table([{"category": p.category, "orientation": p.orientation, "pose": p.pose, "GT": p.n_gt,
                  "missed": p.n_missed, "miss rate": p.miss_rate} for p in picks], title="SCS objects to composite")
    console.print(f"{report.n_missed} of {report.n_gt} evaluated boxes missed; wrote {out}")
    if models_into is not None:
        from omniscs.pipeline.appearance import missed_object_models
        from omniscs.storage import workspace_root

        with progress_bars() as bars:
            models = missed_object_models(out / "missed.json", workspace_root(workspace), models_into,
                                          progress=bars.sink("models of missed objects"))
        print_table([{k: m.get(k) for k in ("store_id", "track_id", "category", "model_id", "reason")}
                     for m in models], title=f"pool models in {models_into}")
        ids = sorted({m["model_id"] for m in models if m["model_id"]})
        console.print(f"{len(ids)} model(s): " + " ".join(f"--appearance-object {m}" for m in ids))
