"""``omniscs fit`` and ``omniscs render``: the Gaussian scene graph of one scene store, through the pipeline's
plan and fit stages."""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional

import typer

from omniscs.checks import MAX_ITERATIONS, MAX_THREADS

from omniscs.cli.common import check_out, console, depth_picture, edited_graph, print_table, progress_bars, read_edits
from omniscs.errors import OmniscsError


#: The stages ``omniscs fit`` can stop after (``--until``): each makes a scene graph.
FIT_STAGES = ("fit", "agents", "background")


def fit(
    scene_path: Path = typer.Argument(..., help="A scene store (see omniscs world make / ingest)."),
    out: Path = typer.Option(..., help="Checkpoint folder to write (must not exist unless --overwrite; a folder "
                                       "holding this very fit is reused)."),
    preset: str = typer.Option("balanced", help="fast, balanced or accurate."),
    iterations: Optional[int] = typer.Option(None, min=1, max=MAX_ITERATIONS,
                                             help="Override the preset's optimiser steps."),
    edit: Optional[str] = typer.Option(None, help="Edits the graph must support (their tracks become nodes): JSON or @file."),
    threads: int = typer.Option(1, min=1, max=MAX_THREADS, help="torch CPU threads."),
    overwrite: bool = typer.Option(False, help="Replace an existing checkpoint at --out."),
    behavior_variants: int = typer.Option(0, help="Behaviour variants will be made with this graph (L_app): "
                                                  "every vehicle becomes a node."),
    device: str = typer.Option("cpu", help="Compute device: cpu or cuda."),
    workspace: Optional[Path] = typer.Option(None, help="Workspace root for the plan (default $OMNISCS_HOME or "
                                                        "./omniscs-data)."),
    pool: Optional[Path] = typer.Option(None, help="Model pool for the dual strategy: tracks the edits turn off their "
                                                   "observed views get a 360-degree model from it (without a pool: "
                                                   "their online model)."),
    background_repair: str = typer.Option("on", help="on: the background behind every large static object the "
                                                     "edits move or remove is repaired (inpainting, relative depth, "
                                                     "DRNet, RoI refit), with the repair's masks, filled views and "
                                                     "depth maps in --out/repair/. off: skip it (for comparison)."),
    until: str = typer.Option("background", help="The last stage to run: fit, agents (360-degree models) or "
                                                 "background (repair); each runs only where the plan needs it. "
                                                 "--out holds the graph of the last one that ran (the earlier ones "
                                                 "stay in the workspace)."),
) -> None:
    """Fit a Gaussian scene graph (background, agent nodes, sky) to a scene store and save a checkpoint: the
    pipeline's stages up to --until, as the plan for the edits needs them."""
    from omniscs.edits import edit_to_dict
    from omniscs.nsg.config import fit_preset
    from omniscs.pipeline.request import SceneRequest
    from omniscs.pipeline.stages import run_directly, start_scene, walk_scene
    from omniscs.pipeline.validate import check_request
    from omniscs.scene import load_scene
    from omniscs.storage import usable_workspace

    # everything checked before anything is written: the scene, the settings, --out and the workspace
    if not scene_path.is_dir():
        raise OmniscsError(f"{scene_path} is not a scene-store directory")
    load_scene(scene_path)
    overrides = {"torch_threads": threads}
    if iterations is not None:
        overrides["iterations"] = iterations
    fit_preset(preset, **overrides)
    if pool is not None and not pool.is_dir():
        raise OmniscsError(f"--pool {pool} is not a pool folder (omniscs pool build / import make one)")
    request = check_request(SceneRequest.parse({
        "fit_preset": preset, "behavior_variants": behavior_variants, "device": device, "previews": False,
        "edits": [edit_to_dict(e) for e in read_edits(edit)], "pool": str(pool) if pool is not None else None}))
    if background_repair not in ("on", "off"):
        raise OmniscsError(f"--background-repair must be on or off; got {background_repair!r}")
    if until not in FIT_STAGES:
        raise OmniscsError(f"--until must be one of {', '.join(FIT_STAGES)}; got {until!r}")
    check_out(out, overwrite=True)  # an existing --out must be a folder omniscs wrote (reused or replaced)
    ws = usable_workspace(workspace)
    skip = ("background",) if background_repair == "off" else ()
    state = walk_scene(start_scene(str(scene_path), request, ws), run_directly(), until="plan")
    planned = state.record("plan")
    plan = state.plan
    console.print(f"plan: {planned.info['summary']}")
    wanted = FIT_STAGES[:FIT_STAGES.index(until) + 1]
    making = [name for name, key in zip(FIT_STAGES, ("fit_nsg", "agent_models", "background_repair"))
              if name in wanted and name not in skip and plan.stages.get(key)]
    last = making[-1]
    if last != "fit" and out.exists() and not overwrite:  # refused before the fit, not after it
        raise OmniscsError(f"{out} already exists; pass --overwrite to replace it")
    options = {"fit": {**overrides, "replace": overwrite}}
    options.setdefault(last, {})["out_dir"] = out
    with progress_bars() as bars:
        state = walk_scene(dataclasses.replace(state, options=options),
                           run_directly(lambda name: bars.sink(f"{planned.scene_id} {name}")), until=until, skip=skip)
    record = state.record("fit")
    if record.info["status"] != "fitted":
        raise OmniscsError(f"the fit of {record.scene_id} diverged: {record.info['error']}")
    agents, repaired = state.ran("agents"), state.ran("background")
    if agents is not None:
        for row in agents.rows["agent_models"]:
            if row["needs_360"]:
                chosen = f" -> {row['pool_model_id']}" if row["pool_model_id"] else ""
                console.print(f"track {row['track_id']}: {row['strategy']}{chosen} ({row['reason']})")
    elif pool is not None:
        console.print("no edit turns an agent off its observed views: the pool was not needed")
    if repaired is not None:
        for row in repaired.rows["background_repairs"]:
            console.print(f"track {row['track_id']}: background repaired in {row['hole_views']} views "
                          f"({row['observed_pixels']:,} px observed elsewhere, {row['plane_pixels']:,} from planes, "
                          f"{row['carried_pixels']:,} carried, "
                          f"{row['inpainted_pixels']:,} inpainted), {row['seeds']:,} Gaussians seeded, "
                          f"{row['seconds']:.0f} s")
    if plan.background_repair and "background" not in making:
        why = "background repair off" if background_repair == "off" else f"background repair not run (--until {until})"
        console.print(f"{why}: the ground behind track(s) {list(plan.background_repair)} stays as fitted")
    m = record.info["metrics"]
    print_table([{"Gaussians": m["n_gaussians"], "agent nodes": m["n_agent_nodes"], "fit s": m["fit_seconds"],
                  "train PSNR": m["train_psnr"], "held-out PSNR": m["heldout_psnr"], "held-out SSIM": m["heldout_ssim"],
                  "held-out views": m["heldout_views"]}], title=f"{record.scene_id} ({preset})")
    verb = "reused" if record.reused and last == "fit" else "wrote"
    console.print(f"{verb} {out} (plan.json, graph.json, gaussians.safetensors, metrics.json"
                  + (", decisions.json" if last == "agents" else "") + (", repair/" if last == "background" else "")
                  + ")")


def render(
    checkpoint: Path = typer.Argument(..., help="A scene-graph checkpoint folder (omniscs fit --out)."),
    out: Path = typer.Option(..., help="PNG to write."),
    camera: str = typer.Option("CAM_FRONT"), frame: int = typer.Option(0),
    edit: Optional[str] = typer.Option(None, help="Edit list as JSON, or @file.json (see README)."),
    ego_pose: Optional[str] = typer.Option(None, help="Render from another ego pose: 'x,y,z,yaw' (world frame, m, rad)."),
    depth: bool = typer.Option(False, help="Append the expected depth beside the image (near is bright)."),
    pool: Optional[Path] = typer.Option(None, help="Model pool whose model ids (pm-...) the edits' replace_model and "
                                                   "insert may name."),
) -> None:
    """Render a fitted (optionally edited) scene graph from a logged camera, at a logged or any ego pose."""
    import numpy as np
    from PIL import Image

    from omniscs.cli.common import comma_list
    from omniscs.geometry import pose_from_xyz_yaw
    from omniscs.nsg.checkpoint import load_graph
    from omniscs.storage import atomic_write_with

    check_out(out, overwrite=True, suffix=".png")
    edits = read_edits(edit)
    world_from_ego = None
    if ego_pose is not None:
        values = comma_list(ego_pose, float, "--ego-pose", "x,y,z,yaw")
        if len(values) != 4 or not np.all(np.isfinite(values)):
            raise OmniscsError(f"--ego-pose must be four numbers x,y,z,yaw; got {ego_pose!r}")
        world_from_ego = pose_from_xyz_yaw(*values)
    graph = edited_graph(load_graph(checkpoint), edits, pool)
    result = graph.render(graph.view(camera, frame, world_from_ego))
    image = (result.rgb.detach().cpu().clamp(0, 1).numpy() * 255).round().astype(np.uint8)
    if depth:
        grey = depth_picture(result.depth.detach().cpu().numpy())
        image = np.concatenate([image, np.repeat(grey[..., None], 3, -1)], 1)
    atomic_write_with(out, lambda buf: Image.fromarray(image).save(buf, format="PNG"))
    console.print(f"wrote {out} ({graph.scene_id}, {camera}, frame {frame}, {len(edits)} edit(s))")
