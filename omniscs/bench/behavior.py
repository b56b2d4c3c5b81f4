"""``omniscs bench behavior``: adversarial success, plausibility, accelerations and time per variant on a fixed
set of procedural scenes, for the loss configurations side by side, plus the traffic model's ADE/FDE."""
from __future__ import annotations

import io
import json
import logging
import textwrap
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from omniscs.edits import SetTrajectory
from omniscs.errors import OmniscsError
from omniscs.bench.harness import finish, load_line, machine_info, report_folder
from omniscs.nsg.checkpoint import load_graph
from omniscs.pipeline.procedural import procedural_traffic
from omniscs.pipeline.request import SceneRequest
from omniscs.pipeline.stages import fit_stage, ingest_stage, load_plan, plan_stage
from omniscs.progress import Progress
from omniscs.scene import SyntheticSource, load_scene
from omniscs.scs.behavior.adversarial_config import AdversarialConfig, adversarial_preset
from omniscs.scs.behavior.render_consistency import masked_psnr, variant_ego_poses
from omniscs.scs.behavior.checkpoint import DEFAULT_CHECKPOINT, checkpoint_hash, load_traffic_model, set_threads
from omniscs.scs.behavior.feasibility import FeasibilityConfig, search_scene
from omniscs.scs.behavior.generation import distinct_variants
from omniscs.scs.behavior.planner import PlannerConfig
from omniscs.scs.behavior.problem import BehaviorProblem
from omniscs.scs.behavior.scene_render import RenderConsistencyConfig, render_variant, scene_graph_render_consistency
from omniscs.scs.behavior.tracks import traffic_from_scene
from omniscs.scs.behavior.train import TRAIN_TEMPLATES
from omniscs.scs.behavior.variants import bev_picture, variant_spec
from omniscs.storage import atomic_write_bytes, atomic_write_json, atomic_write_text, workspace_root
from omniscs.world import WorldRenderer, apply_edits

log = logging.getLogger(__name__)

#: Seeds of benchmark scenes start here (training uses 100_000+, held-out evaluation 900_000+).
BENCH_SEED_OFFSET = 2_000


@dataclass(frozen=True)
class BenchConfig:
    """The fixed benchmark scene set and what runs on it."""

    scenes_per_template: int = 5
    """Procedural scenes per road template (seeds BENCH_SEED_OFFSET + k)."""
    variants_per_scene: int = 2
    """Variants per scene (distinct adversaries first)."""
    seed_offset: int = BENCH_SEED_OFFSET
    """First seed of the scene set (the fixed set starts at BENCH_SEED_OFFSET; another offset is a fresh set)."""
    only_default: bool = False
    """Run only the default configuration on the procedural logs."""
    feasibility: FeasibilityConfig = FeasibilityConfig()
    """The search that decides which scenes some agent can reach (omniscs.scs.behavior.feasibility)."""
    n_frames: int = 40
    """Frames per scene (4 s at 10 Hz: 1 s history, 3 s horizon)."""
    preset: str = "balanced"
    """Adversarial preset the configurations start from."""
    rule_planner: bool = True
    """Also run the default losses against the reacting rule-based planner."""
    torch_threads: int = 1
    """torch CPU threads."""
    appearance_scenes: int = 4
    """Scenes (the first seed of each template, in turn) rendered at 480x270 with one camera and fitted with a
    scene graph, on which the default losses run without and with L_app; 0 skips that comparison."""
    appearance_fit_preset: str = "fast"
    """Scene-graph preset of those fits (every vehicle a node)."""
    appearance_drift_frames: int = 4
    """Horizon frames per variant at which the appearance drift is measured (spread evenly)."""
    app_weights: tuple[float, ...] = (1.0, 30.0)
    """Weights of L_app compared (AdversarialConfig.app_weight); at 1 it is about 1 % of L_beh here."""


DEFAULT = "+ comfort decoding + plausibility penalty (default)"


def configurations(base: AdversarialConfig, rule_planner: bool, only_default: bool = False
                   ) -> dict[str, AdversarialConfig]:
    """The compared loss set-ups on the procedural logs (L_app needs rendered logs: ``appearance_study``)."""
    if only_default:
        return {DEFAULT: base}
    no_penalty = replace(base, comfort_weight=0.0, collision_weight=0.0, offroad_weight=0.0)
    out: dict[str, AdversarialConfig] = {
        "L_beh + L_restore (paper terms without L_app)": replace(no_penalty, comfort_decoding=False),
        "+ comfort decoding": no_penalty,
        DEFAULT: base,
    }
    if rule_planner:
        out["default, rule-based planner"] = replace(base, planner=PlannerConfig(kind="rule"))
    return out


def violation_kind(message: str) -> str:
    """comfort, collision or off_road, from a violation message of ``evaluation.evaluate``."""
    if message.startswith("collision"):
        return "collision"
    if "drivable" in message:
        return "off_road"
    return "comfort"


def _violation_counts(rows: list[dict]) -> dict[str, int]:
    counts: dict[str, int] = {}
    for r in rows:
        for kind in {violation_kind(v) for v in r["violations"]}:
            counts[kind] = counts.get(kind, 0) + 1
    return counts


def scene_reachability(problem: BehaviorProblem, cands: list, search: FeasibilityConfig) -> dict:
    """Both answers to "can some agent reach the ego path": the envelope test (BehaviorProblem.reachable) and the
    feasibility search (stops at the first feasible candidate; envelope-reachable candidates are searched first)."""
    started = time.perf_counter()
    reaches = search_scene(problem, search, stop_at_first=True)
    found = next((r for r in reaches if r.feasible), None)
    return {"reachable": any(c[1] for c in cands), "reachable_agents": sum(c[1] for c in cands),
            "feasible_search": found is not None,
            "feasible_track": None if found is None else int(problem.traffic.track_ids[found.track]),
            "feasible_best_iou": max((r.best_iou for r in reaches), default=0.0),
            "searched_candidates": sum(r.searched for r in reaches),
            "feasibility_seconds": time.perf_counter() - started}


def mark_feasible(scenes: list[dict], rows: dict[str, list[dict]], replay_configs: list[str]) -> None:
    """``feasible``: the search found a trajectory, or some replay-planner configuration made a successful, plausible
    variant (proof the search missed one; counted as ``search_missed``). Same denominator for every configuration."""
    for s in scenes:
        proven = any(r["success"] and r["plausible"] for name in replay_configs for r in rows.get(name, [])
                     if r["scene_id"] == s["scene_id"])
        s["feasible"] = bool(s["feasible_search"] or proven)
        s["search_missed"] = bool(proven and not s["feasible_search"])


def _scene_rates(rows: list[dict], scenes: list[dict], key: str) -> tuple[list[bool], list[bool]]:
    ids = [s["scene_id"] for s in scenes if s.get(key)]
    return ([any(r["success"] for r in rows if r["scene_id"] == sid) for sid in ids],
            [next((r["success"] for r in rows if r["scene_id"] == sid), False) for sid in ids])


def _summary(rows: list[dict], scenes: list[dict]) -> dict:
    if not rows:
        return {}
    succ = [r for r in rows if r["success"]]
    reach_scenes = [s["scene_id"] for s in scenes if s["reachable"]]
    scene_success, scene_first = _scene_rates(rows, scenes, "reachable")
    feas_success, feas_first = _scene_rates(rows, scenes, "feasible")
    lon = np.array([max(-r["adversary_accel"][0], r["adversary_accel"][1]) for r in succ]) if succ else np.zeros(0)
    lat = np.array([r["adversary_max_lateral"] for r in succ]) if succ else np.zeros(0)
    sec = np.array([r["seconds"] for r in rows])
    kinds: dict[str, int] = {}
    for r in succ:
        kinds[r["kind"]] = kinds.get(r["kind"], 0) + 1
    return {
        "variants": len(rows), "successful_variants": len(succ),
        "variant_success_rate": len(succ) / len(rows),
        "reachable_scenes": len(reach_scenes),
        "scene_success_rate_any_variant": float(np.mean(scene_success)) if scene_success else None,
        "scene_success_rate_first_variant": float(np.mean(scene_first)) if scene_first else None,
        "feasible_scenes": len(feas_success),
        "scene_success_rate_feasible": float(np.mean(feas_success)) if feas_success else None,
        "scene_success_rate_feasible_first_variant": float(np.mean(feas_first)) if feas_first else None,
        "failed_feasible_scenes": [s["scene_id"] for s, ok in
                                   zip([s for s in scenes if s.get("feasible")], feas_success) if not ok],
        "violation_rate_successful": (float(np.mean([not r["plausible"] for r in succ])) if succ else None),
        "violation_rate_all": float(np.mean([not r["plausible"] for r in rows])),
        "successful_and_plausible_rate": float(np.mean([r["success"] and r["plausible"] for r in rows])),
        "adversary_abs_long_accel_mean": float(lon.mean()) if len(lon) else None,
        "adversary_abs_long_accel_max": float(lon.max()) if len(lon) else None,
        "adversary_lateral_accel_mean": float(lat.mean()) if len(lat) else None,
        "adversary_lateral_accel_max": float(lat.max()) if len(lat) else None,
        "seconds_per_variant_median": float(np.median(sec)), "seconds_per_variant_mean": float(sec.mean()),
        "iterations_median": float(np.median([r["iterations"] for r in rows])),
        "attempts_mean": float(np.mean([r["attempts"] for r in rows])),
        "knot_variants": sum(r.get("source") == "knots" for r in rows),
        "kinds": kinds,
        "violation_kinds": _violation_counts(rows),
    }


def run_behavior_benchmark(out_dir: Path, config: BenchConfig = BenchConfig(), checkpoint: Path | None = None,
                           progress: Progress | None = None, workspace: Path | None = None) -> dict:
    """Run every configuration on every benchmark scene, then the L_app comparison on rendered scenes (their
    scene stores and scene graphs go to ``workspace`` and are reused); write reports/behavior/report.{json,md,png} and example.png."""
    machine = machine_info()
    previous = set_threads(config.torch_threads)
    try:
        ckpt = Path(checkpoint) if checkpoint else DEFAULT_CHECKPOINT
        model = load_traffic_model(ckpt)
        base = adversarial_preset(config.preset)
        configs = configurations(base, config.rule_planner, config.only_default)
        runnable = configs
        templates = TRAIN_TEMPLATES
        jobs = [(t, config.seed_offset + k) for t in templates for k in range(config.scenes_per_template)]
        rows: dict[str, list[dict]] = {k: [] for k in runnable}
        scenes: list[dict] = []
        total = len(jobs) * len(runnable) * config.variants_per_scene
        done = 0
        example = None
        for template, seed in jobs:
            try:
                traffic = procedural_traffic(template, seed, config.n_frames, scene_id=f"bench-{template}-s{seed}")
            except OmniscsError as exc:
                log.warning("benchmark skips %s seed %d: %s", template, seed, exc)
                done += len(runnable) * config.variants_per_scene
                continue
            started = time.perf_counter()
            problem = BehaviorProblem(traffic, model, base)
            setup_s = time.perf_counter() - started
            cands = problem.candidates()
            scenes.append({"scene_id": traffic.scene_id, "template": template, "seed": seed,
                           "nodes": problem.n_nodes, "candidates": len(cands),
                           **scene_reachability(problem, cands, config.feasibility),
                           "latent_fit_ade_m": problem.fit_ade, "setup_seconds": setup_s})
            for name, cfg in runnable.items():
                problem.config = cfg
                if not cands:
                    done += config.variants_per_scene
                    continue
                made = distinct_variants(problem, cands, config.variants_per_scene)
                done += config.variants_per_scene - len(made)
                for k, v in enumerate(made):
                    ev = v.evaluation
                    rows[name].append({"scene_id": traffic.scene_id, "variant": k, "adversary": v.adversary,
                                       "reachable": v.reachable, "success": ev.success, "plausible": ev.plausible,
                                       "kind": v.kind, "violations": ev.violations,
                                       "adversary_accel": list(ev.adversary_accel),
                                       "adversary_max_lateral": ev.adversary_max_lateral,
                                       "min_distance_m": ev.min_distance_m, "seconds": v.seconds,
                                       "iterations": v.iterations, "attempts": v.attempts,
                                       "source": v.source, "losses": v.losses})
                    if example is None and name.endswith("(default)") and ev.success and ev.plausible:
                        example = (v, traffic)
                    done += 1
                    if progress:
                        progress(done, total)
        mark_feasible(scenes, rows, [n for n, c in runnable.items() if c.planner.kind == "replay"])
        summary = {name: _summary(rows[name], scenes) for name in runnable}
        appearance = appearance_study(model, base, config, workspace) if config.appearance_scenes else None
        training = json.loads((ckpt / "training.json").read_text()) if (ckpt / "training.json").is_file() else {}
        result = {
            "bench": asdict(config), "checkpoint": str(ckpt), "checkpoint_hash": checkpoint_hash(ckpt)[:12],
            "adversarial_config": json.loads(json.dumps(asdict(base), default=str)),
            "configurations": list(configs), "scenes": scenes, "summary": summary, "rows": rows,
            "traffic_model_heldout": training.get("heldout_metrics"),
            "traffic_model_heldout_manoeuvres": training.get("heldout_manoeuvre_metrics"),
            "latent_fit_ade_m_mean": float(np.mean([s["latent_fit_ade_m"] for s in scenes])) if scenes else None,
            "appearance": appearance, "machine": finish(machine),
        }
        folder = report_folder(out_dir, "behavior")
        atomic_write_json(folder / "report.json", result)
        atomic_write_text(folder / "report.md", markdown(result))
        _plot(result, folder / "report.png")
        if example is not None:
            bev_picture(example[0], example[1], folder / "example.png")
        return result
    finally:
        set_threads(previous)


def variant_ground_truth(world, variant: dict, camera: str, frames: list[int]
                         ) -> tuple[np.ndarray, np.ndarray]:  # rgb [T, H, W, 3] in [0, 1], adversary mask [T, H, W]
    """Ground truth for a variant of a procedural log: the world with every agent on its variant trajectory
    (SetTrajectory edits; heights kept from the log), re-rendered, and the adversary's instance mask."""
    if variant.get("source_frames") is None:
        raise OmniscsError("variant steps are not the scene's frames (the log was resampled); no ground truth")
    n = world.n_frames
    edits = []
    by_id = {a.track_id: a for a in world.agents}
    for key, traj in variant["agents"].items():
        agent = by_id.get(int(key))
        if agent is None:
            continue
        waypoints = [None] * n
        for step, pose in zip(variant["source_frames"], traj):
            if pose is not None and 0 <= step < n:
                z = float(agent.poses[step, 2, 3]) if agent.present[step] else float(agent.size[2] / 2)
                waypoints[step] = (pose[0], pose[1], z, pose[2])
        edits.append(SetTrajectory(int(key), tuple(waypoints)))
    edited = apply_edits(world, edits)
    if variant.get("ego") is not None:  # a reacting planner moves the ego too
        edited = edited.replace(ego_poses=variant_ego_poses(variant, edited.ego_poses))
    renderer = WorldRenderer(edited)
    rgb, masks = [], []
    for f in frames:
        r = renderer.render_camera(int(f), camera)
        rgb.append(r.rgb.astype(np.float64) / 255.0)
        masks.append(r.instance == int(variant["adversary"]))
    return np.stack(rgb), np.stack(masks)


#: The L_app comparison's baseline: the default configuration without L_app, on the same scenes.
NO_APP = "default (L_beh + L_restore + penalty)"


def appearance_configs(weights: tuple[float, ...]) -> list[tuple[str, float | None]]:
    """(name, L_app weight or None) of the L_app comparison's set-ups, baseline first."""
    return [(NO_APP, None)] + [(f"default + L_app (weight {w:g})", float(w)) for w in weights]


def appearance_study(model, base: AdversarialConfig, config: BenchConfig, workspace: Path | None = None,
                     progress: Progress | None = None) -> dict:
    """The default losses without and with L_app on rendered logs with fitted scene graphs: success,
    plausibility, time per variant, and the appearance drift (masked PSNR of the scene graph's render of each
    variant against the procedural world re-rendered with the same trajectories, adversary pixels only)."""
    ws = workspace_root(workspace)
    render = RenderConsistencyConfig()
    jobs = [(TRAIN_TEMPLATES[k % len(TRAIN_TEMPLATES)], config.seed_offset + k // len(TRAIN_TEMPLATES))
            for k in range(config.appearance_scenes)]
    setups = appearance_configs(config.app_weights)
    rows: dict[str, list[dict]] = {name: [] for name, _ in setups}
    scenes, fits = [], []
    for template, seed in jobs:
        if progress:
            progress(len(scenes), None, f"L_app comparison: {template} seed {seed}")
        try:
            stored = ingest_stage(SyntheticSource(template, seed, "day", config.n_frames, 1, 480, 270), ws)
        except OmniscsError as exc:
            log.warning("L_app comparison skips %s seed %d: %s", template, seed, exc)
            continue
        scene = load_scene(stored.path)
        request = SceneRequest(fit_preset=config.appearance_fit_preset,
                               behavior_variants=config.variants_per_scene, previews=False)
        plan = load_plan(plan_stage(stored.path, request, ws))
        record = fit_stage(stored.path, plan, config.appearance_fit_preset, ws)
        (fit,) = record.rows["models"]
        fits.append({k: fit.get(k) for k in ("scene_id", "model_id", "status", "n_gaussians", "fit_seconds",
                                              "heldout_psnr", "n_agent_nodes", "reused")})
        if fit["status"] != "fitted":
            continue
        graph = load_graph(fit["checkpoint_path"], scene)
        camera = graph.cameras[0].name
        traffic = traffic_from_scene(scene)
        problem = BehaviorProblem(traffic, model, base)
        cands = problem.candidates()
        scenes.append({"scene_id": traffic.scene_id, "template": template, "seed": seed, "candidates": len(cands),
                       **scene_reachability(problem, cands, config.feasibility), "camera": camera})
        if not cands:
            continue
        term = scene_graph_render_consistency(graph, traffic, model, base, render)
        for name, weight in setups:
            problem.render_consistency = None if weight is None else term
            problem.config = base if weight is None else replace(base, app_weight=weight)
            for k, v in enumerate(distinct_variants(problem, cands, config.variants_per_scene)):
                spec = variant_spec(v)
                horizon = spec["source_frames"][v.now_step + 1:]
                pick = np.unique(np.round(np.linspace(0, len(horizon) - 1, config.appearance_drift_frames)))
                frames = [int(horizon[int(i)]) for i in pick]
                truth, mask = variant_ground_truth(scene.world, spec, camera, frames)
                rendered = render_variant(graph, spec, camera, frames)
                ev = v.evaluation
                rows[name].append({"scene_id": traffic.scene_id, "variant": k, "adversary": v.adversary,
                                   "success": ev.success, "plausible": ev.plausible, "kind": v.kind,
                                   "violations": ev.violations, "adversary_accel": list(ev.adversary_accel),
                                   "adversary_max_lateral": ev.adversary_max_lateral,
                                   "min_distance_m": ev.min_distance_m, "seconds": v.seconds,
                                   "iterations": v.iterations, "attempts": v.attempts, "source": v.source,
                                   "losses": v.losses,
                                   "drift_frames": frames, "adversary_pixels": int(mask.sum()),
                                   "drift_psnr_db": masked_psnr(rendered, truth, mask)})
    mark_feasible(scenes, rows, [name for name, _ in setups])
    summary = {}
    for name, _ in setups:
        s = _summary(rows[name], scenes)
        drift = [r["drift_psnr_db"] for r in rows[name] if r["drift_psnr_db"] is not None]
        s["appearance_drift_psnr_db_mean"] = float(np.mean(drift)) if drift else None
        s["appearance_drift_measured_variants"] = len(drift)
        summary[name] = s
    return {"scenes": scenes, "fits": fits, "rows": rows, "summary": summary,
            "fit_preset": config.appearance_fit_preset, "render": json.loads(json.dumps(asdict(render), default=str))}


def appearance_markdown(study: dict | None) -> list[str]:
    """The L_app table of behaviour's report.md."""
    if not study:
        return ["## What L_app buys", "", "Not run (appearance_scenes = 0).", ""]
    fits = [f for f in study["fits"] if f["status"] == "fitted"]
    r = study["render"]
    lines = ["## What L_app buys (rendered logs, fitted scene graphs)", "",
             f"{len(study['scenes'])} procedural logs rendered at 480x270 with one camera, each fitted with the "
             f"`{study['fit_preset']}` scene-graph preset, every vehicle a node (held-out PSNR "
             + ", ".join(f"{f['heldout_psnr']:.1f}" for f in fits) + " dB). L_app renders "
             f"{r['frames']} horizon frames at 1/{r['downscale']} resolution per optimisation step and compares "
             "them with the unperturbed graph's renders in a fixed random-init CNN's features. Appearance drift: "
             "PSNR of the graph's full-resolution render of each variant against the procedural world re-rendered "
             "with the same trajectories, over the adversary's ground-truth pixels (higher = the perturbed scene "
             "still looks right), at horizon frames where the adversary is seen.", "",
             "| configuration | scene success, feasible scenes | scene success, envelope-reachable scenes | "
             "variant success | violations among successes | "
             "s per variant (median) | appearance drift, adversary PSNR dB (mean) | variants with drift measured |",
             "|---|---|---|---|---|---|---|---|"]
    for name in study["summary"]:
        s = study["summary"][name]
        if not s or "variants" not in s:
            lines.append(f"| {name} | no variants | | | | | | |")
            continue
        lines.append(f"| {name} | {_rate(s, 'scene_success_rate_feasible', 'feasible_scenes')} | "
                     f"{_rate(s, 'scene_success_rate_any_variant', 'reachable_scenes')} | "
                     f"{_fmt(s['variant_success_rate'], True)} ({s['successful_variants']}/{s['variants']}) | "
                     f"{_fmt(s['violation_rate_successful'], True)} | {_fmt(s['seconds_per_variant_median'])} | "
                     f"{_fmt(s['appearance_drift_psnr_db_mean'])} | {s['appearance_drift_measured_variants']} |")
    return lines + [""]


def rerun_appearance_study(out_dir: Path, config: BenchConfig = BenchConfig(), checkpoint: Path | None = None,
                           workspace: Path | None = None) -> dict:
    """Run only the L_app comparison again and replace it in an existing ``out_dir/behavior/report.json`` (and its
    Markdown and plot), leaving the procedural-log tables as they were measured."""
    out_dir = Path(out_dir)
    folder = report_folder(out_dir, "behavior")
    path = folder / "report.json"
    if not path.is_file():
        raise OmniscsError(f"{path} does not exist; run the whole benchmark first")
    result = json.loads(path.read_text())
    previous = set_threads(config.torch_threads)
    try:
        ckpt = Path(checkpoint) if checkpoint else DEFAULT_CHECKPOINT
        if checkpoint_hash(ckpt)[:12] != result.get("checkpoint_hash"):
            raise OmniscsError(f"{path} was measured with checkpoint {result.get('checkpoint_hash')}; the L_app "
                               "comparison must use the same one")
        result["appearance"] = appearance_study(load_traffic_model(ckpt), adversarial_preset(result["bench"]["preset"]),
                                                config, workspace)
        result["bench"]["app_weights"] = list(config.app_weights)
    finally:
        set_threads(previous)
    atomic_write_json(path, result)
    atomic_write_text(folder / "report.md", markdown(result))
    _plot(result, folder / "report.png")
    return result


def _order(result: dict) -> list[str]:
    """Configuration names in the order they were compared (JSON files keep keys sorted)."""
    return result.get("configurations") or list(result["summary"])


def _fmt(x, pct: bool = False) -> str:
    if x is None:
        return "n/a"
    if isinstance(x, str):
        return x
    return f"{100 * x:.0f}%" if pct else f"{x:.2f}"


def _rate(s: dict, key: str, count: str) -> str:
    """'94% (of 16)': a scene success rate with its denominator."""
    if s.get(key) is None and s.get(count) is None:
        return "n/a"
    return f"{_fmt(s.get(key), True)} (of {s.get(count, 0)})"


def _reach_paragraph(scenes: list[dict], search: dict | None) -> str:
    if not scenes or "feasible" not in scenes[0]:  # a report measured before the feasibility search existed
        return (f"{sum(s['reachable'] for s in scenes)} scene(s) have an agent that can reach the ego path by the "
                "envelope test; success rates are over those scenes.")
    n_env = sum(s["reachable"] for s in scenes)
    n_feas = sum(s["feasible"] for s in scenes)
    missed = [s["scene_id"] for s in scenes if s.get("search_missed")]
    env_only = [s["scene_id"] for s in scenes if s["reachable"] and not s["feasible"]]
    feas_only = [s["scene_id"] for s in scenes if s["feasible"] and not s["reachable"]]
    cfg = search or {}
    return (f"Which scenes count: {n_feas} scene(s) are **feasible**: the feasibility search "
            f"(omniscs.scs.behavior.feasibility; {cfg.get('starts', '?')} random starts x up to "
            f"{cfg.get('steps', '?')} Adam steps over free per-step controls of each candidate, rolled through the "
            "bicycle model with the comfort bounds as hard limits, staying on the drivable area"
            + ("" if cfg.get("road", True) else " (off: road ignored)") + ", ignoring other agents, so an upper "
            "bound on any method) found a trajectory whose footprint overlaps the ego's with IoU > 0.02, or a "
            "configuration made a successful, plausible variant there"
            + (f" (the search missed {len(missed)}: {', '.join(missed)})" if missed else " (the search missed none)")
            + f". {n_env} scene(s) are **envelope-reachable** (BehaviorProblem.reachable: +2.4 / -4.05 m/s² along "
            "the fitted path, sideways at most min(4.9 t²/2, 0.2 s²/2), boxes touching), the looser test used "
            "before the search existed."
            + (f" Envelope-reachable but not feasible: {', '.join(env_only)}." if env_only else "")
            + (f" Feasible but not envelope-reachable: {', '.join(feas_only)}." if feas_only else ""))


def markdown(result: dict) -> str:
    scenes = result["scenes"]
    offset = result["bench"].get("seed_offset", BENCH_SEED_OFFSET)
    lines = ["# Behaviour-level SCS benchmark", "",
             f"{len(scenes)} procedural scenes ({', '.join(TRAIN_TEMPLATES)}; seeds from {offset}), "
             f"{result['bench']['variants_per_scene']} variant(s) each, preset `{result['bench']['preset']}`, "
             f"checkpoint `{result['checkpoint_hash']}`. "
             + _reach_paragraph(scenes, result["bench"].get("feasibility")) + " "
             "Success: ego and adversary footprints overlap (IoU > 0.02) at some step; plausible: comfort bounds "
             "(lateral 4.9, +2.4/-4.05 m/s², yaw rate 1 rad/s) for every decoded agent, no collision other than "
             "ego-adversary, nobody leaves the drivable area. Each variant may try up to 3 reachable adversaries; an "
             "adversary that finds no collision is restarted once from a warm start (its latent refitted to a "
             "comfortable interception path found by a search over its control knots), and standing ones start "
             "from it; its time covers all attempts and warm starts. Times: 1 torch thread on a shared 2-core "
             "machine.", ""] + ([load_line(result["machine"]), ""] if result.get("machine") else []) + [
             "| configuration | scene success, feasible scenes (any variant) | scene success, envelope-reachable "
             "scenes (any variant) | scene success, feasible (first variant) | variant success | "
             "violations among successes | violations, all variants | adversary abs(long. accel) mean / max m/s² | "
             "adversary lateral accel mean / max m/s² | s per variant (median) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name in _order(result):
        s = result["summary"][name]
        lines.append(
            f"| {name} | {_rate(s, 'scene_success_rate_feasible', 'feasible_scenes')} | "
            f"{_rate(s, 'scene_success_rate_any_variant', 'reachable_scenes')} | "
            f"{_fmt(s.get('scene_success_rate_feasible_first_variant'), True)} | "
            f"{_fmt(s['variant_success_rate'], True)} "
            f"({s['successful_variants']}/{s['variants']}) | {_fmt(s['violation_rate_successful'], True)} | "
            f"{_fmt(s['violation_rate_all'], True)} | {_fmt(s['adversary_abs_long_accel_mean'])} / "
            f"{_fmt(s['adversary_abs_long_accel_max'])} | {_fmt(s['adversary_lateral_accel_mean'])} / "
            f"{_fmt(s['adversary_lateral_accel_max'])} | {_fmt(s['seconds_per_variant_median'])} |")
    failed = {name: result["summary"][name].get("failed_feasible_scenes") for name in _order(result)}
    if any(failed.values()):
        lines += ["", "Feasible scenes a configuration failed: " + "; ".join(
            f"{name}: {', '.join(v)}" for name, v in failed.items() if v) + "."]
    if scenes and "feasibility_seconds" in scenes[0]:
        lines += ["", f"Feasibility search time per scene: median "
                  f"{np.median([s['feasibility_seconds'] for s in scenes]):.1f} s (not part of the times above)."]
    knots = {name: result["summary"][name].get("knot_variants") for name in _order(result)}
    if any(knots.values()):
        lines += ["", "Variants whose adversary follows its interception path (knot fallback: the latent "
                  "optimisation failed, the control-knot path is successful and plausible): " + "; ".join(
                      f"{name}: {k}" for name, k in knots.items() if k) + "."]
    lines += ["", "Collision kinds among successful variants: " + "; ".join(
        f"{name}: {result['summary'][name].get('kinds')}" for name in _order(result)
        if "kinds" in result["summary"][name]), ""]
    lines += appearance_markdown(result.get("appearance"))
    heldout = result.get("traffic_model_heldout")
    if heldout:
        lines += [f"## Traffic model on held-out procedural scenes ({heldout['horizon_s']:.1f} s horizon)", "",
                  "| agents | posterior (reconstruction) ADE / FDE m | prior mean ADE / FDE m | best of 6 prior "
                  "samples ADE / FDE m | constant velocity ADE / FDE m |", "|---|---|---|---|---|"]
        for label, metrics in (("logged futures", heldout), ("manoeuvre-augmented futures",
                                                             result.get("traffic_model_heldout_manoeuvres"))):
            if not metrics:
                continue
            for group in ("all", "moving"):
                m = metrics[group]
                best = next(k for k in m if k.startswith("prior_min_of_"))
                lines.append(f"| {label}, {group} ({m['agents']}) | {m['posterior']['ade']:.2f} / "
                             f"{m['posterior']['fde']:.2f} | {m['prior_mean']['ade']:.2f} / {m['prior_mean']['fde']:.2f} "
                             f"| {m[best]['ade']:.2f} / {m[best]['fde']:.2f} | {m['constant_velocity']['ade']:.2f} / "
                             f"{m['constant_velocity']['fde']:.2f} |")
        lines.append("")
    if result.get("latent_fit_ade_m_mean") is not None:
        lines.append(f"Latent fit to the log before optimisation: mean ADE {result['latent_fit_ade_m_mean']:.2f} m "
                     "over the benchmark scenes.")
    return "\n".join(lines) + "\n"


def _plot(result: dict, out_png: Path) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(_order(result))
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.8), dpi=110)
    x = np.arange(len(names))
    succ = [result["summary"][n].get("scene_success_rate_feasible") or 0.0 for n in names]
    vsucc = [result["summary"][n]["variant_success_rate"] for n in names]
    viol = [result["summary"][n]["violation_rate_successful"] or 0.0 for n in names]
    axes[0].bar(x - 0.27, succ, 0.27, label="scene success, feasible scenes (any variant)")
    axes[0].bar(x, vsucc, 0.27, label="variant success")
    axes[0].bar(x + 0.27, viol, 0.27, label="violations among successes")
    axes[0].axhline(0.9, color="green", ls="--", lw=0.8)
    axes[0].axhline(0.05, color="red", ls="--", lw=0.8)
    labels = [textwrap.fill(n, 22) for n in names]
    axes[0].set_xticks(x, labels, fontsize=7)
    axes[0].set_ylim(0, 1.05)
    axes[0].legend(fontsize=7)
    axes[0].set_title("targets: success >= 90% (green), violations <= 5% (red)", fontsize=9)
    times = [[r["seconds"] for r in result["rows"][n]] for n in names]
    axes[1].boxplot(times, showfliers=True)
    axes[1].set_xticks(x + 1, labels, fontsize=7)
    axes[1].set_ylabel("seconds per variant (1 thread)")
    axes[1].set_title("optimisation time per variant", fontsize=9)
    fig.suptitle("behaviour-level SCS on procedural logs (L_app comparison: see report.md)", fontsize=9)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return atomic_write_bytes(out_png, buf.getvalue())

