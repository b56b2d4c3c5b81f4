"""``omniscs bench plan``: model only what a scene requires, measured. The same request (edits + behaviour
variants) runs through the pipeline's stages twice per scene, once with the scene's plan and once with every
track modelled as an agent node; wall time per stage, Gaussians, nodes, held-out PSNR and the edited agent's
PSNR against the procedural world re-rendered with the same edit."""
from __future__ import annotations

import dataclasses
import logging
import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from omniscs.bench.fit import EDIT_PROTOCOL, edited_agents, evaluation_views
from omniscs.bench.harness import drop_partial, finish, load_line, machine_info, save_partial, write_report
from omniscs.edits import edit_from_dict, edit_to_dict
from omniscs.nsg.checkpoint import load_graph
from omniscs.nsg.config import fit_preset
from omniscs.nsg.edit import apply_graph_edits
from omniscs.quality import psnr
from omniscs.pipeline.request import SceneRequest
from omniscs.pipeline.stages import behavior_stage, fit_stage, ingest_stage, load_plan, plan_stage
from omniscs.progress import Progress, no_progress
from omniscs.scene import SyntheticSource, load_scene
from omniscs.storage import workspace_root
from omniscs.world import WorldRenderer, apply_edits

log = logging.getLogger(__name__)

#: The two ways of modelling a scene that the benchmark compares.
MODES = ("planned", "every track a node")


@dataclass(frozen=True)
class PlanBenchConfig:
    """Scenes and request of the plan benchmark (held-out seeds: no other benchmark or test uses them)."""

    scenes: tuple[tuple[str, int], ...] = (("straight", 31), ("t_junction", 32), ("intersection", 33))
    """(template, seed) of each procedural scene."""
    n_frames: int = 40
    """Frames per scene (every 4th held out)."""
    n_cameras: int = 3
    """Cameras per frame."""
    width: int = 480
    """Image width."""
    height: int = 270
    """Image height."""
    fit_preset: str = "fast"
    """Scene-graph preset of both modes."""
    behavior_variants: int = 1
    """Behaviour variants requested per scene (L_app rendered by the fitted graph)."""
    behavior_preset: str = "fast"
    """Behaviour optimisation preset."""
    edit: str = "translate 2.0 m"
    """The protocol edit (``bench.fit.EDIT_PROTOCOL``) requested on the scene's most visible agent."""
    views: int = 4
    """Views of the edited agent compared with the ground truth."""
    min_pixels: int = 200
    """A view counts when the edited agent covers at least this many ground-truth pixels."""


def run_plan_benchmark(out_dir: Path, config: PlanBenchConfig = PlanBenchConfig(), workspace: Path | None = None,
                       progress: Progress = no_progress) -> dict:
    """Both modes on every scene; returns (and writes as reports/plan/report.*) rows and medians."""
    machine = machine_info()
    ws = workspace_root(workspace)
    spec = dict(EDIT_PROTOCOL)[config.edit]
    rows = []
    with tempfile.TemporaryDirectory(prefix="omniscs-bench-plan-") as tmp:  # stage outputs are made afresh
        for template, seed in config.scenes:
            source = SyntheticSource(template, seed, "day", config.n_frames, config.n_cameras, config.width,
                                     config.height)
            progress(len(rows), 2 * len(config.scenes), f"scene {source.scene_id()}")
            ingested = ingest_stage(source, ws)
            scene = load_scene(ingested.path)
            (target,) = edited_agents(scene, (), 1, config.min_pixels) or (None,)
            if target is None:
                log.warning("%s: no agent covers %d pixels; skipped", scene.scene_id, config.min_pixels)
                continue
            edit = edit_from_dict({**spec, "track_id": target})
            request = SceneRequest(fit_preset=config.fit_preset, behavior_variants=config.behavior_variants,
                                   behavior_preset=config.behavior_preset, edits=(edit_to_dict(edit),),
                                   previews=False)
            truth = WorldRenderer(apply_edits(scene.world, [edit]))
            views = evaluation_views(truth, scene, target, config.views, config.min_pixels)
            for mode in MODES:
                progress(len(rows), 2 * len(config.scenes), f"{scene.scene_id}: {mode}")
                plan_config = dataclasses.replace(fit_preset(config.fit_preset).plan,
                                                  every_track_a_node=mode != "planned")
                stage_ws = Path(tmp) / mode.replace(" ", "-")
                rows.append(_run_mode(ingested.path, request, plan_config, stage_ws, mode, edit, views))
                rows[-1].update(template=template, seed=seed, edited_track=target)
                save_partial(out_dir, "plan", rows)
    progress(len(rows), len(rows), "done")
    report = {"config": dataclasses.asdict(config), "machine": finish(machine), "rows": rows,
              "summary": _summary(rows)}
    write_report(out_dir, "plan", report, markdown(report), {"": lambda buf: _plot(report, buf)})
    drop_partial(out_dir, "plan")
    return report


def _run_mode(scene_path: str, request: SceneRequest, plan_config, workspace: Path, mode: str, edit,
              views) -> dict:
    started = time.perf_counter()
    planned = plan_stage(scene_path, request, workspace, plan_config=plan_config)
    plan = load_plan(planned)
    fitted = fit_stage(scene_path, plan, request.fit_preset, workspace, reuse=False)
    if fitted.info["status"] != "fitted":
        return {"mode": mode, "scene_id": planned.scene_id, "status": "diverged", "error": fitted.info["error"]}
    variants = behavior_stage(scene_path, plan, request.behavior_variants, workspace, request.behavior_preset,
                              model=fitted, reuse=False)
    wall = time.perf_counter() - started
    metrics = fitted.info["metrics"]
    graph = apply_graph_edits(load_graph(fitted.path), [edit])
    edited = []
    for f, cam, gt in views:
        with torch.no_grad():
            out = graph.render(graph.view(cam, f))
        target = torch.from_numpy(gt.rgb.astype(np.float32) / 255.0)
        edited.append(psnr(out.rgb, target, torch.from_numpy(gt.instance == edit.track_id)))
    finite = [v for v in edited if v is not None]
    return {"mode": mode, "scene_id": planned.scene_id, "status": "fitted", "wall_s": wall,
            "fit_s": fitted.seconds, "behavior_s": variants.seconds, "n_agent_nodes": len(plan.agent_nodes),
            "n_tracks": len(plan.agent_nodes) + len(plan.background_tracks), "gaussian_budget": plan.gaussian_budget,
            "n_gaussians": metrics["n_gaussians"], "heldout_psnr": metrics["heldout_psnr"],
            "heldout_ssim": metrics["heldout_ssim"], "edited_views": len(finite),
            "edited_masked_psnr": float(np.mean(finite)) if finite else None,
            "variant_success": variants.info.get("n_success"), "node_reasons": plan.node_reasons}


def _summary(rows: list[dict]) -> list[dict]:
    out = []
    for mode in MODES:
        r = [x for x in rows if x["mode"] == mode and x["status"] == "fitted"]
        if not r:
            continue
        edited = [x["edited_masked_psnr"] for x in r if x["edited_masked_psnr"] is not None]
        out.append({"mode": mode, "scenes": len(r),
                    **{f"median_{k}": statistics.median(x[k] for x in r)
                       for k in ("wall_s", "fit_s", "behavior_s", "n_agent_nodes", "n_gaussians", "heldout_psnr")},
                    "median_edited_masked_psnr": statistics.median(edited) if edited else None})
    planned = {x["scene_id"]: x for x in rows if x["mode"] == MODES[0] and x["status"] == "fitted"}
    every = {x["scene_id"]: x for x in rows if x["mode"] == MODES[1] and x["status"] == "fitted"}
    pairs = [(planned[s], every[s]) for s in planned if s in every]
    if pairs and out:
        out[0]["median_time_ratio_vs_every_track"] = statistics.median(p["wall_s"] / e["wall_s"] for p, e in pairs)
        out[0]["median_heldout_psnr_delta_db"] = statistics.median(p["heldout_psnr"] - e["heldout_psnr"]
                                                                   for p, e in pairs)
    return out


def _f(v, digits: int = 2) -> str:
    return "n/a" if v is None else f"{v:.{digits}f}"


def markdown(report: dict) -> str:
    c = report["config"]
    lines = ["# Model only what a scene requires: planned vs every track a node", "",
             f"Request per scene: the `{c['edit']}` edit on its most visible agent, {c['behavior_variants']} "
             f"behaviour variant(s) (`{c['behavior_preset']}`, L_app rendered by the fitted graph); scene graph "
             f"preset `{c['fit_preset']}`; {c['n_frames']} frames x {c['n_cameras']} cameras at "
             f"{c['width']}x{c['height']}, every 4th frame held out. Both modes run the pipeline's plan, fit and "
             "behaviour stages afresh; only the plan differs. Edited-agent PSNR: the edited graph against the "
             "procedural world re-rendered with the same edit, over the agent's ground-truth mask.", "",
             load_line(report["machine"]), "",
             "| mode | scenes | median wall (s) | median fit (s) | median variants (s) | median nodes | "
             "median Gaussians | median held-out PSNR (dB) | median edited-agent PSNR (dB) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for s in report["summary"]:
        lines.append(f"| {s['mode']} | {s['scenes']} | {s['median_wall_s']:.0f} | {s['median_fit_s']:.0f} | "
                     f"{s['median_behavior_s']:.0f} | {s['median_n_agent_nodes']:.0f} | "
                     f"{s['median_n_gaussians']:,.0f} | {s['median_heldout_psnr']:.2f} | "
                     f"{_f(s['median_edited_masked_psnr'])} |")
    if report["summary"] and "median_time_ratio_vs_every_track" in report["summary"][0]:
        s = report["summary"][0]
        lines += ["", f"Planned / every-track wall time (median of per-scene ratios): "
                      f"{s['median_time_ratio_vs_every_track']:.2f}; held-out PSNR difference (planned minus "
                      f"every-track, median): {s['median_heldout_psnr_delta_db']:+.2f} dB."]
    lines += ["", "Per scene:", "", "| scene | mode | nodes / tracks | wall (s) | fit (s) | variants (s) | Gaussians | "
              "held-out PSNR | edited-agent PSNR (views) | variant hit |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in report["rows"]:
        if r["status"] != "fitted":
            lines.append(f"| {r['scene_id']} | {r['mode']} | diverged: {r['error']} | | | | | | | |")
            continue
        lines.append(f"| {r['scene_id']} | {r['mode']} | {r['n_agent_nodes']} / {r['n_tracks']} | {r['wall_s']:.0f} | "
                     f"{r['fit_s']:.0f} | {r['behavior_s']:.0f} | {r['n_gaussians']:,} | {r['heldout_psnr']:.2f} | "
                     f"{_f(r['edited_masked_psnr'])} ({r['edited_views']}) | {r['variant_success']} |")
    return "\n".join(lines) + "\n"


def _plot(report: dict, buf) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
    colours = {MODES[0]: "tab:green", MODES[1]: "tab:red"}
    rows = [r for r in report["rows"] if r["status"] == "fitted"]
    for mode in MODES:
        r = [x for x in rows if x["mode"] == mode]
        ax.scatter([x["wall_s"] / 60 for x in r], [x["heldout_psnr"] for x in r], color=colours[mode], label=mode)
    by_scene: dict[str, dict] = {}
    for x in rows:
        by_scene.setdefault(x["scene_id"], {})[x["mode"]] = x
    for pair in by_scene.values():
        if len(pair) == 2:
            a, b = pair[MODES[0]], pair[MODES[1]]
            ax.plot([a["wall_s"] / 60, b["wall_s"] / 60], [a["heldout_psnr"], b["heldout_psnr"]], color="grey",
                    lw=0.8, ls=":")
    ax.set_xlabel("pipeline wall time per scene (min)")
    ax.set_ylabel("held-out PSNR (dB)")
    ax.set_title("Planned vs every track a node (dotted: same scene)", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(buf, format="png")
    plt.close(fig)
