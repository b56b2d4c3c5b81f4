"""``omniscs bench dataset``: how fast the factory turns fitted scenes into annotated variants.

Per held-out procedural scene: ingest, plan, fit (fast preset; reused from the workspace when present, it is not
what this measures) and behaviour variants, the replay of the logged views (once per fitted graph; timed on its own
and reported both apart and counted against the scene's variants), then the render + annotate stage is timed from scratch: the ego's
solution, rendering, annotation (masks, boxes, visibility, own-alpha renders, simulated LiDAR), writing, and the
fidelity measures. Three set-ups price the fidelity knob: the default (exact comparison with the world's render plus
the proxies), the proxies only (what a recorded log costs; the headline number) and none; then, for throughput at
the nuScenes size, one variant through a 6-camera 1600x900 rig (the graph renders any camera; no fidelity there).
Last, every annotated variant is exported as OpenSCENARIO + OpenDRIVE and checked with ASAM's checkers
(``omniscs.bench.openscenario``: ``openscenario.json`` / ``.md`` beside the report)."""
from __future__ import annotations

import json
import logging
import statistics
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import pandas as pd

from omniscs.annotate import AnnotateConfig
from omniscs.annotate.scene import read_rows
from omniscs.annotate.variant import write_annotated_variant
from omniscs.bench.harness import finish, load_line, machine_info, write_report
from omniscs.bench.openscenario import write_openscenario_report
from omniscs.nsg.checkpoint import load_graph
from omniscs.pipeline.request import SceneRequest
from omniscs.pipeline.stages import (annotate_stage, behavior_stage, fit_stage, ingest_stage, load_plan, plan_stage,
                                     replay_stage)
from omniscs.progress import Progress, no_progress
from omniscs.scene import SyntheticSource, load_scene
from omniscs.scene.store import MANIFEST, CameraRecord
from omniscs.storage import workspace_root
from omniscs.world import camera_rig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DatasetBenchConfig:
    """Scenes, rig and request of the dataset benchmark (held-out seeds: no other benchmark or test uses them)."""

    scenes: tuple[tuple[str, int], ...] = (("straight", 51), ("t_junction", 52))
    """(template, seed) of each procedural scene."""
    n_frames: int = 40
    """Frames per scene (the target's 40 frames)."""
    n_cameras: int = 3
    """Cameras of the logged rig."""
    width: int = 480
    """Image width of the logged rig."""
    height: int = 270
    """Image height of the logged rig."""
    variants: int = 2
    """Behaviour variants per scene."""
    fit_preset: str = "fast"
    """Scene-graph preset."""
    behavior_preset: str = "fast"
    """Behaviour optimisation preset."""
    big_rig: tuple[int, int, int] = (6, 1600, 900)
    """(cameras, width, height) of the nuScenes-size rendering."""
    big_frame_every: int = 4
    """The nuScenes-size rendering renders every Nth frame of one variant per scene (it is slow)."""
    target_variants_per_hour: float = 300.0
    """The issue's target at 480x270, 3 cameras, 40 frames, on 2 cores."""


def _per_image(summary: dict) -> dict:
    n = max(int(summary["n_images"]), 1)
    return {"images": summary["n_images"], "render_ms": 1e3 * summary["render_seconds"] / n,
            "annotate_ms": 1e3 * summary["annotate_seconds"] / n, "write_ms": 1e3 * summary["write_seconds"] / n,
            "total_ms": 1e3 * summary["seconds"] / n, "images_per_s": n / max(summary["seconds"], 1e-9)}


def run_dataset_benchmark(out_dir: str | Path, workspace: str | Path | None = None,
                          config: DatasetBenchConfig = DatasetBenchConfig(),
                          progress: Progress = no_progress) -> dict:
    machine = machine_info()
    ws = workspace_root(workspace)
    request = SceneRequest(fit_preset=config.fit_preset, behavior_variants=config.variants,
                           behavior_preset=config.behavior_preset, annotate=True, previews=False)
    scenes, variant_stores = [], []
    for template, seed in config.scenes:
        source = SyntheticSource(template=template, seed=seed, n_frames=config.n_frames, n_cameras=config.n_cameras,
                                 width=config.width, height=config.height)
        progress(0, None, f"{template}:{seed}: ingest, fit, variants")
        scene_rec = ingest_stage(source, ws)
        plan_rec = plan_stage(scene_rec.path, request, ws)
        plan = load_plan(plan_rec)
        fitted = fit_stage(scene_rec.path, plan, config.fit_preset, ws)
        behaved = behavior_stage(scene_rec.path, plan, config.variants, ws, config.behavior_preset, model=fitted)
        progress(0, None, f"{template}:{seed}: replay of the logged views")
        replayed = replay_stage(scene_rec.path, fitted, ws, reuse=False)  # once per graph: timed on its own
        row = {"scene": f"{template}:{seed}", "scene_id": scene_rec.scene_id,
               "fit_seconds": fitted.info.get("metrics", {}).get("fit_seconds"),
               "heldout_psnr": fitted.info.get("metrics", {}).get("heldout_psnr"),
               "behavior_seconds": behaved.seconds, "variants": behaved.info["n_variants"],
               "replay_seconds": replayed.seconds, "replay_views": replayed.info["n_views"]}
        for label, annotate_config in (("with fidelity", AnnotateConfig()),
                                       ("proxies only", AnnotateConfig(exact_fidelity=False)),
                                       ("without fidelity", AnnotateConfig(fidelity_every=0))):
            progress(0, None, f"{template}:{seed}: render + annotate ({label})")
            started = time.perf_counter()
            rec = annotate_stage(scene_rec.path, plan, fitted, behaved, ws, config=annotate_config, reuse=False)
            stage_s = time.perf_counter() - started
            rows = read_rows(rec.path)
            summaries = rows["variants"]
            total = {k: sum(v[k] for v in summaries) for k in ("n_images", "render_seconds", "annotate_seconds",
                                                               "write_seconds", "seconds")}
            with_replay = stage_s + (replayed.seconds if annotate_config.fidelity_every else 0.0)
            row[label] = {"stage_seconds": stage_s, "seconds_per_variant": stage_s / max(len(summaries), 1),
                          "variants_per_hour": 3600.0 * len(summaries) / stage_s,
                          "variants_per_hour_with_replay": 3600.0 * len(summaries) / with_replay, **_per_image(total),
                          "ego_solved": sum(bool(v["ego_solved"]) for v in summaries),
                          "fidelity_psnr": [v["fidelity_psnr"] for v in summaries],
                          "fidelity_masked_psnr": [v["fidelity_masked_psnr"] for v in summaries],
                          "dropped_frames": sum(v["dropped_frames"] for v in summaries),
                          "feature_drift": [v.get("feature_drift") for v in summaries],
                          "psnr_drift_pairs": [(r["fidelity_psnr"], r["feature_drift"], r["logged_psnr"])
                                               for r in rows["samples"]
                                               if r.get("fidelity_psnr") is not None
                                               and r.get("feature_drift") is not None
                                               and r.get("logged_psnr") is not None]}
        # nuScenes size: one variant through a 6-camera 1600x900 rig, every Nth frame
        scene = load_scene(scene_rec.path)
        graph = load_graph(fitted.path, scene)
        variant = json.loads(Path(behaved.path).read_text())[0]
        n, w, h = config.big_rig
        rig = [CameraRecord(c.name, c.width, c.height, c.K, c.ego_from_camera) for c in camera_rig(n, w, h)]
        progress(0, None, f"{template}:{seed}: render + annotate at {w}x{h} x {n}")
        big = write_annotated_variant(graph, scene, variant, ws / "bench-dataset" / f"{scene.scene_id}-big",
                                      f"{scene.scene_id}-big", rig=rig,
                                      config=AnnotateConfig(frame_every=config.big_frame_every, fidelity_every=0))
        row["nuscenes size"] = _per_image(big.summary)
        scenes.append(row)
        variant_stores += sorted(p for p in Path(rec.path).iterdir() if (p / MANIFEST).is_file())
    result = {"config": asdict(config), "scenes": scenes, "machine": finish(machine)}
    result["summary"] = summarise(scenes, config)
    write_report(out_dir, "dataset", result, markdown(result), {"": lambda f: _plot(result, f)})
    progress(0, None, f"OpenSCENARIO export of {len(variant_stores)} variant(s) and ASAM's checkers")
    result["openscenario"] = write_openscenario_report(out_dir, variant_stores,
                                                       ws / "bench-dataset" / "openscenario")["summary"]
    return result


def summarise(scenes: list[dict], config: DatasetBenchConfig) -> dict:
    def med(label: str, key: str) -> float:
        return float(statistics.median(s[label][key] for s in scenes))

    pairs = np.array([p for sc in scenes for p in sc["with fidelity"]["psnr_drift_pairs"]], np.float64).reshape(-1, 3)

    def spearman(a: np.ndarray, b: np.ndarray) -> float | None:
        if len(a) < 3 or np.ptp(a) == 0 or np.ptp(b) == 0:
            return None
        return float(pd.Series(a).corr(pd.Series(b), method="spearman"))

    drop = pairs[:, 2] - pairs[:, 0]  # how much the variant frame is worse than the unedited logged frame
    return {"variants_per_hour": med("proxies only", "variants_per_hour"),
            "variants_per_hour_with_replay": med("proxies only", "variants_per_hour_with_replay"),
            "replay_seconds": float(statistics.median(sc["replay_seconds"] for sc in scenes)),
            "replay_views": int(statistics.median(sc["replay_views"] for sc in scenes)),
            "variants_per_hour_with_fidelity": med("with fidelity", "variants_per_hour"),
            "variants_per_hour_without_fidelity": med("without fidelity", "variants_per_hour"),
            "drift_psnr_spearman": spearman(pairs[:, 1], pairs[:, 0]),
            "drift_drop_spearman": spearman(pairs[:, 1], drop),
            "logged_psnr_spearman": spearman(pairs[:, 2], pairs[:, 0]),
            "drift_psnr_samples": int(len(pairs)),
            "images_per_s_480x270": med("without fidelity", "images_per_s"),
            "images_per_s_nuscenes_size": med("nuscenes size", "images_per_s"),
            "target_variants_per_hour": config.target_variants_per_hour,
            "meets_target": med("proxies only", "variants_per_hour") >= config.target_variants_per_hour}


def markdown(result: dict) -> str:
    c, s = result["config"], result["summary"]
    lines = ["# Dataset benchmark: render + annotate throughput", "", load_line(result["machine"]), "",
             f"Held-out procedural scenes {', '.join(f'{t}:{k}' for t, k in c['scenes'])}; {c['n_frames']} frames, "
             f"{c['n_cameras']} cameras at {c['width']}x{c['height']}; {c['variants']} behaviour variant(s) per scene "
             f"({c['behavior_preset']} preset) on a {c['fit_preset']}-preset scene graph. Times are of the render + "
             "annotate stage run from scratch (the ego's solution, rendering, annotation, writing the variant's "
             "store and, per set-up, the fidelity measures); fitting, variant generation and the replay of the "
             "logged views (once per fitted graph, timed on its own below) are not included (\"after fitting\"). "
             "Medians over scenes. Set-ups: *with fidelity* = the default (exact comparison "
             "with the world's render plus the proxies, every frame); *proxies only* = `exact_fidelity=False` (logged "
             "PSNR and feature drift, as a recorded log gets them); *without fidelity* = `fidelity_every=0`.", "",
             f"**{s['variants_per_hour']:.0f} annotated variants per hour** ({c['n_frames']} frames x "
             f"{c['n_cameras']} cameras, {c['width']}x{c['height']}: the ego's solution, rendering, every annotation, "
             "the fidelity proxies on every frame, the variant's store; what a recorded log costs). Target "
             f"{s['target_variants_per_hour']:.0f}: {'met' if s['meets_target'] else 'not met'}. The replay that the "
             f"proxies read (every logged view rendered once per fitted graph, {s['replay_views']} views) takes "
             f"{s['replay_seconds']:.1f} s per scene; counted against this benchmark's {c['variants']} variants per "
             f"scene it gives {s['variants_per_hour_with_replay']:.0f} variants per hour (each further annotate run "
             "on the same graph, e.g. more variants, reads it again for free). The exact fidelity "
             "comparison, a check only procedural scenes can have (the world renders every frame again exactly, then "
             f"PSNR/SSIM; on by default there), costs more than all the rest: "
             f"{s['variants_per_hour_with_fidelity']:.0f} variants per hour with it; "
             f"{s['variants_per_hour_without_fidelity']:.0f} with no fidelity measured at all.", "",
             "| scene | set-up | images | render ms/img | annotate ms/img | write ms/img | total ms/img | images/s | "
             "s/variant | variants/h | ego solved | variant PSNR dB (masked) | feature drift |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|"]
    for sc in result["scenes"]:
        for label in ("with fidelity", "proxies only", "without fidelity", "nuscenes size"):
            r = sc[label]
            psnr = ", ".join(f"{p:.1f} ({m:.1f})" if p is not None and m is not None else "n/a"
                             for p, m in zip(r.get("fidelity_psnr", []), r.get("fidelity_masked_psnr", [])))
            big = label == "nuscenes size"
            setup = f"{c['big_rig'][1]}x{c['big_rig'][2]} x {c['big_rig'][0]} cams, every {c['big_frame_every']}th " \
                    "frame, no fidelity" if big else label
            lines.append(f"| {sc['scene']} | {setup} | {r['images']} | {r['render_ms']:.1f} | {r['annotate_ms']:.1f} | "
                         f"{r['write_ms']:.1f} | {r['total_ms']:.1f} | {r['images_per_s']:.2f} | "
                         + ("" if big else f"{r['seconds_per_variant']:.1f}") + " | "
                         + ("" if big else f"{r['variants_per_hour']:.0f}") + " | "
                         + ("" if big else f"{r['ego_solved']}/{sc['variants']}") + f" | {psnr if not big else ''} | "
                         + ", ".join(f"{d:.3f}" for d in r.get("feature_drift", []) if d is not None) + " |")
    lines += ["", "Per scene: fit " + ", ".join(
        f"{sc['scene']} {sc['fit_seconds'] or 0:.0f} s (held-out PSNR {sc['heldout_psnr'] or 0:.1f} dB)"
        for sc in result["scenes"]) + "; behaviour variants " + ", ".join(
        f"{sc['behavior_seconds']:.0f} s" for sc in result["scenes"]) + " (reused from the workspace when 0).",
        "", "Render = the rasterisation of colour, depth and the per-instance label channels; annotate = masks, boxes, each visible instance rendered alone for its own alpha and simulated "
        "LiDAR; write = what the rendering waited for the writer thread that encodes PNG and compressed ground "
        "truth beside it. With fidelity, render also holds reading the logged view's unedited render from the "
        "replay and the feature drift. The rest of a variant's time (\"other\" in the plot) is the ego's solution, the exact "
        "reference render of the procedural world, PSNR/SSIM and the variant's bookkeeping. At the nuScenes size there is no exact reference (the world's "
        "rig is the logged one), so no fidelity is measured there.", "",
        "Recorded logs have no exact image of an edited scene, so they get two proxies (`omniscs.annotate."
        "fidelity`), both from the scene graph's unedited render of the logged view: `logged_psnr` (that render "
        "against the logged image: how well the graph reproduces the frame) and `feature_drift` (the variant frame "
        "against that render, edited agents left out: what the edit and the new viewpoint changed). On these "
        f"procedural scenes, where the exact PSNR is known ({s['drift_psnr_samples']} images), Spearman "
        f"correlations: logged PSNR with the exact PSNR {_num(s['logged_psnr_spearman'])}; drift with the exact "
        f"PSNR {_num(s['drift_psnr_spearman'])}; drift with the PSNR lost against the unedited frame (logged PSNR "
        f"minus exact PSNR) {_num(s['drift_drop_spearman'])}. The right panel of the plot shows the last."]
    return "\n".join(lines) + "\n"


def _num(x: float | None) -> str:
    return "n/a (too few or constant values)" if x is None else f"{x:.2f}"


def _plot(result: dict, f) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = ("with fidelity", "proxies only", "without fidelity", "nuscenes size")
    parts = ("render_ms", "annotate_ms", "write_ms")
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 4), dpi=110, gridspec_kw={"width_ratios": [3, 2]})
    x = np.arange(len(labels))
    bottom = np.zeros(len(labels))
    for part in parts:
        vals = np.array([statistics.median(s[label][part] for s in result["scenes"]) for label in labels])
        ax.bar(x, vals, bottom=bottom, label=part.replace("_ms", ""))
        bottom += vals
    other = np.array([statistics.median(s[label]["total_ms"] for s in result["scenes"]) for label in labels]) - bottom
    ax.bar(x, np.clip(other, 0, None), bottom=bottom, label="other (solution, exact reference, PSNR/SSIM)", color="0.7")
    c = result["config"]
    ax.set_xticks(x, [f"{c['width']}x{c['height']}\nexact + proxies", f"{c['width']}x{c['height']}\nproxies only",
                      f"{c['width']}x{c['height']}\nno fidelity",
                      f"{c['big_rig'][1]}x{c['big_rig'][2]}\nno fidelity"])
    ax.set_ylabel("ms per annotated image (median over scenes)")
    ax.set_title(f"render + annotate with proxies: {result['summary']['variants_per_hour']:.0f} variants/h, "
                 f"{result['summary']['variants_per_hour_with_replay']:.0f} with the replay "
                 f"(target {c['target_variants_per_hour']:.0f})", fontsize=10)
    ax.legend(fontsize=8)
    for sc in result["scenes"]:
        pairs = np.array(sc["with fidelity"]["psnr_drift_pairs"], np.float64).reshape(-1, 3)
        bx.scatter(pairs[:, 1], pairs[:, 2] - pairs[:, 0], s=6, alpha=0.6, label=sc["scene"])
    rho = result["summary"]["drift_drop_spearman"]
    bx.set_xlabel("feature drift vs the unedited render (recorded-log proxy)")
    bx.set_ylabel("PSNR lost vs the unedited frame, dB")
    bx.set_title("proxy vs exact fidelity per image" + ("" if rho is None else f" (Spearman {rho:.2f})"))
    bx.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(f, format="png")
    plt.close(fig)


def quick_config() -> DatasetBenchConfig:
    """A tiny set-up for tests of the benchmark's code path (not for numbers)."""
    return replace(DatasetBenchConfig(), scenes=(("straight", 51),), n_frames=16, width=96, height=54, variants=1,
                   big_rig=(2, 160, 90), big_frame_every=5)
