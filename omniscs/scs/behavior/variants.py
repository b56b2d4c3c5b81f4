"""Behaviour variants on disk: the JSON spec (``variants.json``), a BEV picture per variant, catalog rows,
and the one call that makes them for a scene (used by the CLI and the flow task)."""
from __future__ import annotations

import io
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from omniscs.gates import GateConfig, behaviour_verdict
from omniscs.scs.behavior.adversarial_config import AdversarialConfig
from omniscs.scs.behavior.render_consistency import RenderConsistencyTerm
from omniscs.scs.behavior.checkpoint import DEFAULT_CHECKPOINT, checkpoint_hash, load_traffic_model
from omniscs.scs.behavior.collision import footprints
from omniscs.scs.behavior.evaluation import VariantResult
from omniscs.scs.behavior.generation import generate_variants
from omniscs.scs.behavior.tracks import TrafficScene
from omniscs.storage import atomic_write_bytes, atomic_write_json

log = logging.getLogger(__name__)

VARIANTS_JSON = "variants.json"
SPEC_VERSION = 1
#: Metres shown around the ego path and the adversary in a BEV picture.
BEV_MARGIN_M = 18.0


def _rows(a: np.ndarray) -> list:
    """[S, 3] with NaN rows -> [[x, y, yaw] or None, ...] rounded to mm / mrad."""
    return [None if not np.all(np.isfinite(r)) else [round(float(r[0]), 3), round(float(r[1]), 3),
                                                     round(float(r[2]), 4)] for r in a]


def _finite(x):
    if x is None:
        return None
    return float(x) if math.isfinite(float(x)) else None


def variant_spec(v: VariantResult) -> dict:
    """The JSON-serialisable spec of one variant (world frame; positions are box centres)."""
    ev = v.evaluation
    sizes = {"ego": [round(v.ego_size[0], 3), round(v.ego_size[1], 3)]}
    sizes.update({str(k): [round(s[0], 3), round(s[1], 3)] for k, s in sorted(v.sizes.items())})
    return {
        "variant_id": v.variant_id,
        "scene_id": v.scene_id,
        "dt": v.dt,
        "ego": _rows(v.ego),
        "agents": {str(k): _rows(a) for k, a in sorted(v.agents.items())},
        "sizes": sizes,
        "adversary": int(v.adversary),
        "collision_step": v.collision_step,
        "collision_time_s": None if v.collision_step is None else round(v.collision_step * v.dt, 3),
        "success": bool(ev.success),
        "plausible": bool(ev.plausible),
        "losses": {k: _finite(val) for k, val in v.losses.items()},
        "kind": v.kind,
        "violations": list(ev.violations),
        "reachable": bool(v.reachable),
        "now_step": int(v.now_step),
        "beh_window_steps": [v.now_step + 1 + v.window[0], v.now_step + 1 + v.window[1] - 1],
        "timestamps_us": [int(t) for t in v.timestamps_us],
        "source_frames": None if v.source_frames is None else [int(f) for f in v.source_frames],
        "planner": v.planner,
        "ego_centre_ahead_of_origin_m": v.ego_centre_ahead_m,
        "min_distance_m": round(ev.min_distance_m, 3),
        "adversary_accel_mps2": [round(ev.adversary_accel[0], 3), round(ev.adversary_accel[1], 3)],
        "adversary_max_lateral_accel_mps2": round(ev.adversary_max_lateral, 3),
        "adversary_max_yaw_rate_radps": round(ev.adversary_max_yaw_rate, 4),
        "iterations": v.iterations,
        "attempts": v.attempts,
        "source": v.source,
        "seconds": round(v.seconds, 3),
        "collision_point": None if v.collision_point is None else [round(float(c), 3) for c in v.collision_point],
        "spec_version": SPEC_VERSION,
    }


def catalog_row(v: VariantResult, variants_json: Path, bev_png: Path | None, checkpoint: str) -> dict:
    """One row of the ``variants`` catalog table."""
    ev = v.evaluation
    return {
        "scene_id": v.scene_id, "variant_id": v.variant_id, "kind": v.kind, "adversary": int(v.adversary),
        "collision_step": v.collision_step,
        "collision_time_s": None if v.collision_step is None else v.collision_step * v.dt,
        "success": bool(ev.success), "plausible": bool(ev.plausible), "reachable": bool(v.reachable),
        "n_violations": len(ev.violations), "violations": list(ev.violations),
        "loss_adv": _finite(v.losses.get("L_adv")), "loss_beh": _finite(v.losses.get("L_beh")),
        "loss_app": _finite(v.losses.get("L_app")), "loss_restore": _finite(v.losses.get("L_restore")),
        "loss_plaus": _finite(v.losses.get("L_plaus")),
        "adversary_min_accel_mps2": ev.adversary_accel[0], "adversary_max_accel_mps2": ev.adversary_accel[1],
        "adversary_max_lateral_accel_mps2": ev.adversary_max_lateral, "min_distance_m": ev.min_distance_m,
        "planner": v.planner, "iterations": v.iterations, "attempts": v.attempts, "source": v.source,
        "optimisation_seconds": v.seconds,
        "checkpoint": checkpoint, "variants_path": str(variants_json),
        "bev_path": None if bev_png is None else str(bev_png),
    }


# ----------------------------------------------------------------------------- BEV picture
def bev_picture(v: VariantResult, traffic: TrafficScene, out_png: Path) -> Path:
    """Original (dashed) against adversarial (solid) trajectories over the map, the adversary in red, the ego
    plan in black, boxes at the first contact (or closest approach) and the collision point. Written atomically."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from omniscs.preview import track_colour

    ego, adv = v.ego, v.agents[v.adversary]
    focus = np.vstack([ego, adv[np.isfinite(adv[:, 0])], v.original_agents[v.adversary][
        np.isfinite(v.original_agents[v.adversary][:, 0])]])[:, :2]
    lo, hi = focus.min(0) - BEV_MARGIN_M, focus.max(0) + BEV_MARGIN_M
    span = hi - lo
    fig, ax = plt.subplots(figsize=(10.0, float(np.clip(10.0 * span[1] / span[0], 3.5, 10.0))), dpi=110)
    m = traffic.map
    h, w = m.shape
    extent = (m.origin[0], m.origin[0] + w * m.resolution, m.origin[1], m.origin[1] + h * m.resolution)
    background = np.where(m.layers[0] > 0.5, 0.72, 0.93)
    background = np.where(m.layers[1] > 0.5, 0.62, background)
    ax.imshow(background, origin="lower", extent=extent, cmap="gray", vmin=0, vmax=1, zorder=0,
              interpolation="nearest")
    t_mark = v.collision_step
    if t_mark is None:
        t_mark = v.now_step + 1 + int(np.argmin(np.linalg.norm(ego[v.now_step + 1:, :2] - adv[v.now_step + 1:, :2],
                                                               axis=1)))
    now = v.now_step
    for tid, traj in v.agents.items():
        if tid == v.adversary:
            continue
        orig = v.original_agents[tid]
        if not np.any(np.all((orig[:, :2] >= lo) & (orig[:, :2] <= hi), axis=1) & np.isfinite(orig[:, 0])):
            continue
        colour = np.array(track_colour(tid)) / 255.0
        moved = np.nanmax(np.linalg.norm(traj[:, :2] - orig[:, :2], axis=1), initial=0.0) > 0.05
        ax.plot(orig[:, 0], orig[:, 1], "--", color=colour, lw=0.9, alpha=0.8, zorder=2)
        if moved:
            ax.plot(traj[now:, 0], traj[now:, 1], "-", color=colour, lw=1.3, zorder=3)
        if np.isfinite(traj[t_mark, 0]):
            fp = footprints(traj[t_mark, :2], traj[t_mark, 2], v.sizes[tid][0], v.sizes[tid][1])
            ax.fill(fp[:, 0], fp[:, 1], color=colour, alpha=0.45, zorder=3, lw=0)
    ax.plot(v.original_ego[:, 0], v.original_ego[:, 1], "--", color="0.25", lw=1.2, zorder=4, label="ego (log)")
    ax.plot(ego[:, 0], ego[:, 1], "-", color="black", lw=2.2, zorder=5, label=f"ego plan ({v.planner})")
    orig_adv = v.original_agents[v.adversary]
    ax.plot(orig_adv[:, 0], orig_adv[:, 1], "--", color="tab:red", lw=1.2, zorder=4,
            label=f"adversary {v.adversary} (log)")
    ax.plot(adv[now:, 0], adv[now:, 1], "-", color="tab:red", lw=2.2, zorder=5,
            label=f"adversary {v.adversary} (variant)")
    for traj, size, colour in ((ego, v.ego_size, "black"), (adv, v.sizes[v.adversary], "tab:red")):
        fp = footprints(traj[t_mark, :2], traj[t_mark, 2], size[0], size[1])
        ax.fill(fp[:, 0], fp[:, 1], facecolor="none", edgecolor=colour, lw=1.8, zorder=6)
        fp0 = footprints(traj[now, :2], traj[now, 2], size[0], size[1])
        ax.fill(fp0[:, 0], fp0[:, 1], color=colour, alpha=0.25, zorder=5, lw=0)
    if v.collision_point is not None:
        ax.plot(*v.collision_point, marker="*", color="gold", markeredgecolor="black", markersize=18, zorder=7,
                label=f"collision, t = {v.collision_step * v.dt:.1f} s")
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, world)")
    ax.set_ylabel("y (m, world)")
    status = "collision" if v.success else "no collision"
    plaus = "plausible" if v.plausible else f"{len(v.evaluation.violations)} violation(s)"
    ax.set_title(f"{v.scene_id} {v.variant_id}: {v.kind}, {status}, {plaus}; L_beh {v.losses['L_beh']:.2f}, "
                 f"L_restore {v.losses['L_restore']:.2f}\nfaint boxes: now (t = {now * v.dt:.1f} s); outlined: "
                 f"{'first contact' if v.success else 'closest approach'} (t = {t_mark * v.dt:.1f} s); "
                 "dashed = log, solid = variant", fontsize=8)
    ax.legend(loc="upper left", fontsize=7, framealpha=0.85)
    ax.grid(True, alpha=0.25)
    fig.tight_layout()
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)

    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return atomic_write_bytes(out_png, buf.getvalue())


# ----------------------------------------------------------------------------- one scene
@dataclass
class VariantsOutput:
    """What ``write_scene_variants`` produced."""

    variants: list[VariantResult]
    variants_json: Path
    bev_pngs: list[Path]
    rows: list[dict]
    reused: bool


def write_scene_variants(traffic: TrafficScene, out_dir: Path, n_variants: int, checkpoint: Path | str | None = None,
                         config: AdversarialConfig = AdversarialConfig(),
                         render_consistency: RenderConsistencyTerm | None = None, pictures: bool = True,
                         progress: Callable[[int, int], None] | None = None,
                         published_dir: Path | None = None, gates: GateConfig | None = None,
                         budget: int | None = None) -> VariantsOutput:
    """Generate ``n_variants`` variants of ``traffic`` and write ``out_dir/variants.json`` (+ one BEV PNG each,
    and ``catalog_rows.json``). ``published_dir``: where the folder will finally live when ``out_dir`` is a
    temporary one (the catalog rows name files there). With ``gates``, each variant gets its verdict (``gate`` in
    its spec, ``passed_gates`` and ``gate_reasons`` in its row) and further candidates are tried, up to ``budget``
    variants in all, until ``n_variants`` pass; every variant tried is written. Whether to reuse earlier variants
    is the caller's decision (the behavior stage's key)."""
    out_dir = Path(out_dir)
    final_dir = Path(published_dir) if published_dir is not None else out_dir
    ckpt = Path(checkpoint) if checkpoint is not None else DEFAULT_CHECKPOINT
    model = load_traffic_model(ckpt)
    ckpt_hash = checkpoint_hash(ckpt)
    target = out_dir / VARIANTS_JSON
    started = time.perf_counter()
    accept = None if gates is None else (lambda v: behaviour_verdict(variant_spec(v), gates).passed)
    results = generate_variants(traffic, model, n_variants, config, render_consistency, progress, accept, budget)
    specs = [variant_spec(v) for v in results]
    if gates is not None:
        for spec in specs:
            spec["gate"] = behaviour_verdict(spec, gates).to_dict()
    pngs = [bev_picture(v, traffic, out_dir / f"{v.variant_id}.png") for v in results] if pictures else []
    atomic_write_json(target, specs)
    rows = [catalog_row(v, final_dir / VARIANTS_JSON, final_dir / pngs[i].name if pngs else None, ckpt_hash[:12])
            for i, v in enumerate(results)]
    for row, spec in zip(rows, specs):
        if "gate" in spec:
            row.update(passed_gates=spec["gate"]["passed"], gate_reasons=spec["gate"]["reasons"])
    atomic_write_json(out_dir / "catalog_rows.json", rows)
    log.info("%d variant(s) of %s in %.1f s -> %s", len(results), traffic.scene_id, time.perf_counter() - started,
             target)
    return VariantsOutput(results, target, pngs, rows, False)
