"""``omniscs bench background --replacement``: a large parked object replaced by a smaller one, with and without the
background repair behind it, measured against the procedural world with the same replacement.

An appearance variant that replaces a parked trailer or truck by a sedan keeps the object's motion (it stands where
the trailer stood) but covers only part of its footprint; the rest shows what the fitted graph has behind the trailer,
which no camera saw: a smeared, trailer-shaped ghost. On held-out procedural logs with a large parked object (the
removal benchmark's; of each log's large static objects the one the cameras see most), a pool model of a smaller kind
(the asset library's pool split, so no benchmark world holds it) replaces the object in the fitted graph as it is ('no
repair', what the factory did before) and in the graph the background stage repaired ('repaired', the same repair and
key as for a removal); both are rendered at held-out logged views and at novel views (the ego shifted sideways) and
compared with the world, with the same replacement, ray-cast. The region scored is the uncovered footprint: the old
object's pixels in the world with it, less the new object's pixels in the world with the replacement. Ghost share: the
share of that region where the render differs from the exact image by more than ``ghost_threshold`` grey levels on
some channel; hole PSNR over the same region.
"""
from __future__ import annotations

import statistics
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from omniscs.agents.pool import Pool, model_resolver
from omniscs.background.repair import RepairConfig
from omniscs.bench.agents import build_pool
from omniscs.bench.background import BackgroundBenchConfig, prepare_scene, render_eval
from omniscs.bench.harness import finish, load_line, machine_info, write_report
from omniscs.errors import OmniscsError
from omniscs.nsg.checkpoint import load_graph
from omniscs.nsg.edit import node_model_resolver
from omniscs.pipeline.background import background_stage
from omniscs.pipeline.procedural import appearance_world, pool_asset_of
from omniscs.plan import PlanConfig
from omniscs.progress import Progress, no_progress
from omniscs.quality import psnr
from omniscs.scene.summary import agent_rows
from omniscs.scs.appearance.compose import compose_variant, replace_variant
from omniscs.storage import workspace_root
from omniscs.world import WorldRenderer
from omniscs.world.assets import list_asset_ids

#: The benchmark's part of ``reports/background/``.
PART = "replacement"
ARMS = ("no repair", "repaired")
#: Categories of the objects replaced (the removal benchmark's).
LARGE_CATEGORIES = ("truck", "trailer", "bus", "construction_vehicle")


@dataclass(frozen=True)
class ReplacementBenchConfig:
    """Which logs, which smaller object, which views and what counts as a ghost."""

    scenes: tuple[str, ...] = BackgroundBenchConfig().scenes
    """Held-out procedural logs (template:seed) with a large parked object: the removal benchmark's."""
    preset: str = "fast"
    """Fit preset of the scene graphs (the fits are the removal benchmark's, reused)."""
    n_frames: int = 40
    """Frames per log."""
    object_kind: str = "sedan"
    """Asset kind of the replacing object (its first model of the library's pool split)."""
    offsets_m: tuple[float, ...] = (-1.5, 1.5)
    """Novel views: the ego shifted this far sideways (+ = left) at the held-out frames."""
    views_per_kind: int = 12
    """At most this many evaluated views per scene and kind (logged, each novel offset), spread evenly."""
    min_region_pixels: int = 400
    """An evaluated view shows at least this many pixels of the uncovered footprint (full resolution)."""
    ghost_threshold: int = 24
    """A pixel of the uncovered footprint is ghost where the render differs from the exact image by more than this
    many grey levels (0..255) on some channel: well above the fitted background's own error on the road and walls
    around (a few grey levels), well below a trailer's side against the road."""
    repair: RepairConfig = field(default_factory=RepairConfig)
    """The background stage's repair settings."""


def quick_config() -> ReplacementBenchConfig:
    """A small run: the log of ``make demo``'s dataset (its 13 m trailer) at 20 frames, one novel offset, the
    background stage's own repair; one log, so a smoke run rather than a measurement across logs."""
    return ReplacementBenchConfig(scenes=("straight_parked_truck:3",), n_frames=20, offsets_m=(1.5,), views_per_kind=6)


def ghost_scores(rgb: np.ndarray,    # [H, W, 3] uint8 render
                 truth: np.ndarray,  # [H, W, 3] uint8 exact image of the edited world
                 region: np.ndarray,  # [H, W] bool uncovered footprint
                 threshold: int) -> dict:
    """Ghost pixels (region pixels off by more than ``threshold`` grey levels on some channel), their share of the
    region, and the region's PSNR (None for an empty region)."""
    n = int(region.sum())
    off = np.abs(rgb.astype(np.int16) - truth.astype(np.int16)).max(-1) > threshold
    ghost = int((off & region).sum())
    value = psnr(torch.from_numpy(rgb.astype(np.float32) / 255.0), torch.from_numpy(truth.astype(np.float32) / 255.0),
                 torch.from_numpy(region)) if n else None
    return {"region_pixels": n, "ghost_pixels": ghost, "ghost_share": ghost / n if n else None, "hole_psnr": value}


@dataclass
class ReplacementView:
    kind: str                  # "logged" or "novel +1.5 m"
    camera: str
    frame: int
    world_from_ego: np.ndarray  # [4, 4] the (possibly shifted) ego pose
    truth: np.ndarray          # [H, W, 3] uint8 the world with the replacement
    region: np.ndarray         # [H, W] bool old object's pixels not covered by the new object


def shifted_world(world, offset_m: float):
    """``world`` with the ego moved ``offset_m`` sideways (+ = left) at every frame."""
    shift = np.eye(4)
    shift[1, 3] = offset_m
    return world.replace(ego_poses=world.ego_poses @ shift)


def uncovered_region(with_old, with_new, track: int, frame: int, camera: str) -> tuple[np.ndarray, np.ndarray]:
    """(exact RGB of the edited world [H, W, 3] uint8, the uncovered footprint [H, W] bool) at one view: the pixels
    where track ``track`` is the first surface in ``with_old`` (a WorldRenderer of the world as logged) and not in
    ``with_new`` (of the world with the replacement, the same track id)."""
    old = with_old.render_camera(frame, camera).instance == track
    new = with_new.render_camera(frame, camera)
    return new.rgb, old & (new.instance != track)


def replacement_views(world, edited, track: int, frames, cameras, config: ReplacementBenchConfig
                      ) -> list[ReplacementView]:
    """Held-out logged views and novel views whose uncovered footprint has at least ``min_region_pixels`` pixels,
    at most ``views_per_kind`` per kind spread evenly over the frames (``world``: as logged; ``edited``: with the
    replacement)."""
    out = []
    for offset in (0.0,) + tuple(config.offsets_m):
        w = world if offset == 0 else shifted_world(world, offset)
        e = edited if offset == 0 else shifted_world(edited, offset)
        with_old, with_new = WorldRenderer(w), WorldRenderer(e)
        found = []
        for f in frames:
            for cam in cameras:
                truth, region = uncovered_region(with_old, with_new, track, int(f), cam)
                if region.sum() >= config.min_region_pixels:
                    found.append((int(f), cam, truth, region))
        if len(found) > config.views_per_kind:  # evenly over the frames, not the easiest or hardest views
            found = [found[int(i)] for i in np.linspace(0, len(found) - 1, config.views_per_kind).round()]
        kind = "logged" if offset == 0 else f"novel {offset:+.1f} m"
        out += [ReplacementView(kind, cam, f, w.ego_poses[f], truth, region) for f, cam, truth, region in found]
    return out


def most_visible_large_object(scene) -> int:
    """The track id of the scene's static truck, trailer, bus or construction vehicle of at least the plan's large
    volume that the cameras see most of (largest mask in any view): where a ghost would show."""
    large = PlanConfig().large_object_volume_m3
    rows = [a for a in agent_rows(scene)
            if not a["moving"] and a["category"] in LARGE_CATEGORIES
            and a["length"] * a["width"] * a["height"] >= large]
    if not rows:
        raise OmniscsError(f"scene {scene.scene_id} has no large static object to replace")
    return int(max(rows, key=lambda a: (a["max_visible_pixels"] or 0, a["track_id"]))["track_id"])


def replacement_pool(workspace: Path, kind: str, progress: Progress = no_progress) -> tuple[Pool, str]:
    """The benchmark's pool (``<workspace>/pools/bench-replacement``) holding the first pool-split model of ``kind``,
    and that model's id."""
    ids = list_asset_ids(kind, "pool")[:1]
    if not ids:
        raise OmniscsError(f"the asset library has no {kind!r} model in its pool split; pick another object_kind")
    root = Path(workspace) / "pools" / "bench-replacement"
    build_pool(root, ids, progress)
    pool = Pool(root)
    table = pool.table()
    row = table[(table.provenance == "mesh") & (table.source == ids[0])]
    return pool, str(row.iloc[0].model_id)


def run_scene(item: str, config: ReplacementBenchConfig, workspace: Path, pool: Pool, model_id: str,
              progress: Progress = no_progress) -> dict:
    scene, plan, fitted, track = prepare_scene(item, config.preset, workspace, progress, n_frames=config.n_frames,
                                               pick=most_visible_large_object)
    t0 = time.perf_counter()
    repaired_record = background_stage(scene.path, plan, fitted, workspace, progress=progress, config=config.repair)
    repair_seconds = time.perf_counter() - t0
    graphs = {"no repair": load_graph(fitted.path, scene), "repaired": load_graph(repaired_record.path, scene)}
    resolve = model_resolver(pool.root, None)
    model = resolve(model_id)
    variant = replace_variant(scene.scene_id, "r000", track, model, model_id)
    composed = {arm: compose_variant(g, variant, model_resolver(pool.root, node_model_resolver(g))).graph
                for arm, g in graphs.items()}
    edited = appearance_world(scene.world, variant, pool_asset_of(pool))
    views = replacement_views(scene.world, edited, track, plan.heldout_frames, scene.camera_names, config)
    per_view = {arm: [] for arm in ARMS}
    strip = None
    strip_view = max((v for v in views if v.kind != "logged"), key=lambda v: v.region.sum(), default=None)
    for v in views:
        renders = {}
        for arm in ARMS:
            rgb, _ = render_eval(composed[arm], v)
            renders[arm] = rgb
            per_view[arm].append({"kind": v.kind, **ghost_scores(rgb, v.truth, v.region, config.ghost_threshold)})
        if v is strip_view:
            strip = {"truth": v.truth, "region": v.region, **renders,
                     "label": f"{scene.scene_id} {v.camera} frame {v.frame} {v.kind}"}
    rows = []
    for arm in ARMS:
        for kind in ("logged", "novel"):
            sel = [r for r in per_view[arm] if r["kind"].startswith(kind)]
            region = sum(r["region_pixels"] for r in sel)
            ghost = sum(r["ghost_pixels"] for r in sel)
            rows.append({"scene_id": scene.scene_id, "track_id": track, "arm": arm, "views": kind, "n_views": len(sel),
                         "region_pixels": region, "ghost_pixels": ghost,
                         "ghost_share": ghost / region if region else None,
                         "hole_psnr": _mean([r["hole_psnr"] for r in sel])})
    old = graphs["no repair"].agent(track)
    facts = {"scene_id": scene.scene_id, "source": item, "track_id": track, "category": old.category,
             "size": [float(x) for x in old.size], "object_id": model_id, "object_size": [float(x) for x in model.size],
             "repair_seconds": repair_seconds, "repair_reused": repaired_record.reused,
             "eval_views": {k: sum(v.kind.startswith(k) for v in views) for k in ("logged", "novel")}}
    return {"rows": rows, "facts": facts, "strip": strip}


def _mean(values) -> float | None:
    vals = [v for v in values if v is not None and np.isfinite(v)]
    return float(statistics.fmean(vals)) if vals else None


def summary(rows: list[dict]) -> list[dict]:
    """Per arm and kind of view: ghost share pooled over the scenes' regions, mean hole PSNR over the scenes."""
    out = []
    for arm in ARMS:
        for kind in ("logged", "novel"):
            sel = [r for r in rows if r["arm"] == arm and r["views"] == kind]
            region = sum(r["region_pixels"] for r in sel)
            out.append({"arm": arm, "views": kind, "scenes": len(sel), "n_views": sum(r["n_views"] for r in sel),
                        "region_pixels": region, "ghost_pixels": sum(r["ghost_pixels"] for r in sel),
                        "ghost_share": sum(r["ghost_pixels"] for r in sel) / region if region else None,
                        "hole_psnr": _mean([r["hole_psnr"] for r in sel])})
    return out


def run_replacement_benchmark(out_dir: Path, workspace: Path | None = None,
                              config: ReplacementBenchConfig = ReplacementBenchConfig(),
                              progress: Progress = no_progress) -> dict:
    workspace = Path(workspace) if workspace else workspace_root()
    machine = machine_info()
    started = time.perf_counter()
    pool, model_id = replacement_pool(workspace, config.object_kind, progress)
    rows, facts, strips = [], [], []
    for item in config.scenes:
        result = run_scene(item, config, workspace, pool, model_id, progress)
        rows += result["rows"]
        facts.append(result["facts"])
        if result["strip"] is not None:
            strips.append(result["strip"])
    report = {"config": asdict(config), "machine": finish(machine), "seconds": time.perf_counter() - started,
              "rows": rows, "scenes": facts, "summary": summary(rows)}
    write_report(out_dir, "background", report, replacement_markdown(report),
                 {"": lambda buf: strip_png(strips, buf)} if strips else None, part=PART)
    return report


def replacement_markdown(report: dict) -> str:
    def f(v, d=2):
        return "—" if v is None else f"{v:.{d}f}"

    c = report["config"]
    lines = [
        "# A large parked object replaced by a smaller one (`omniscs bench background --replacement`)", "",
        f"Procedural logs {', '.join(c['scenes'])} ({c['n_frames']} frames x 3 cameras at 480x270, fit preset "
        f"{c['preset']}); of each log's large parked trucks and trailers, the one the cameras see most is replaced by "
        f"a pool {c['object_kind']} (its own "
        "size, the object's pose, resting on the same ground) in the fitted graph as it is ('no repair') and in the "
        "graph the background stage repaired ('repaired'), and compared with the world with the same replacement at "
        f"held-out logged views and novel views (ego shifted {', '.join(f'{o:+.1f}' for o in c['offsets_m'])} m "
        "sideways). Region: the old object's pixels less the new object's (the uncovered footprint). Ghost: region "
        f"pixels off by more than {c['ghost_threshold']} grey levels on some channel. "
        + load_line(report["machine"]) + f" Total {report['seconds'] / 60:.1f} min.", "",
        "| arm | views | views scored | region pixels | ghost pixels | ghost share | hole PSNR (dB) |",
        "|---|---|---|---|---|---|---|"]
    for r in report["summary"]:
        share = "—" if r["ghost_share"] is None else f"{100 * r['ghost_share']:.1f} %"
        lines.append(f"| {r['arm']} | {r['views']} | {r['n_views']} | {r['region_pixels']:,} | {r['ghost_pixels']:,} | "
                     f"{share} | {f(r['hole_psnr'])} |")
    lines += ["", "| scene | object | size (m) | replaced by | size (m) | repair (s) |", "|---|---|---|---|---|---|"]
    for s in report["scenes"]:
        size = " x ".join(f"{x:.1f}" for x in s["size"])
        lines.append(f"| {s['scene_id']} | {s['category']} {s['track_id']} | {size} "
                     f"| {s['object_id']} | {' x '.join(f'{x:.1f}' for x in s['object_size'])} | "
                     f"{f(s['repair_seconds'], 1)}{' (reused)' if s['repair_reused'] else ''} |")
    lines += ["", "![replacement](replacement.png)", "",
              "One novel view per scene: the world with the replacement (exact), no repair, repaired; the uncovered "
              "footprint outlined in red.", ""]
    return "\n".join(lines)


def strip_png(strips: list[dict], buf) -> None:
    import cv2
    from PIL import Image

    rows = []
    for s in strips:
        edge = cv2.morphologyEx(s["region"].astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
        tiles = []
        for key in ("truth",) + ARMS:
            img = s[key].copy()
            img[edge] = (255, 0, 0)
            tiles.append(img)
        rows.append(np.concatenate(tiles, 1))
    sheet = Image.fromarray(np.concatenate(rows, 0))
    sheet.save(buf, format="PNG", optimize=True)
