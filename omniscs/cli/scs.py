"""``omniscs scs``: behaviour-level safety-critical scenario synthesis (train the traffic model, make variants)."""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Optional

import typer

from omniscs.cli.common import check_out, console, print_table, progress_bars
from omniscs.errors import OmniscsError

app = typer.Typer(help="Safety-critical scenario synthesis (behaviour-level variants).", no_args_is_help=True)


@app.command("train-behavior")
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
    threads: int = typer.Option(1, help="torch CPU threads."),
    nsg: Optional[Path] = typer.Option(None, help="The scene's fitted scene graph (omniscs fit --behavior-variants "
                                                  "N): adds L_app, rendered by it."),
    app_frames: int = typer.Option(3, help="L_app: horizon steps rendered per optimisation step."),
    app_downscale: int = typer.Option(4, help="L_app: render at 1/N of the camera resolution."),
) -> None:
    """Behaviour-level SCS: perturb agents' latents so one of them collides with the ego plan, plausibly."""
    from omniscs.pipeline.procedural import traffic_for_source
    from omniscs.scene import SyntheticSource, parse_source
    from omniscs.scs.behavior import PlannerConfig, adversarial_preset, now_and_horizon, write_scene_variants
    from omniscs.scs.behavior.checkpoint import load_checkpoint
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
    now_and_horizon(traffic, load_checkpoint(checkpoint).config, config)  # user errors before any progress bar
    appearance = None
    if nsg is not None:
        from omniscs.scene import load_scene
        from omniscs.scs.behavior.scene_render import AppearanceRenderConfig, appearance_from_checkpoint

        if isinstance(source, SyntheticSource):
            raise OmniscsError("--nsg needs a rendered scene store (a syn: log has no images to fit a graph to)")
        appearance = appearance_from_checkpoint(nsg, load_scene(Path(scene)), traffic, checkpoint, config,
                                                AppearanceRenderConfig(frames=app_frames, downscale=app_downscale))
    with progress_bars() as bars:
        result = write_scene_variants(traffic, out, variants, checkpoint, config, appearance,
                                      progress=bars.sink(f"variants of {traffic.scene_id}"))
    if not result.rows:
        raise OmniscsError(f"scene {traffic.scene_id} has no vehicle besides the ego at the now step; "
                           "no behaviour variant can be made")
    print_table([{"variant": r["variant_id"], "kind": r["kind"], "hit": r["success"], "plausible": r["plausible"],
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
