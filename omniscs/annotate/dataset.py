"""A dataset: the annotated variants of one or more scenes gathered under ``datasets/<dataset_id>/``.

Layout::

    scenes/<store id>/   one scene store per variant (hard links to the annotate stage's stores: no copy)
    bev/<store id>.png   the variant's BEV with the ego's plan, the adversary and the ego's solution
    preview.png          contact sheet: rendered frames with instance masks and boxes drawn
    dataset.json         the card: sources, config, counts, fidelity summary (README.md says the same in prose)
"""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np

from omniscs.annotate.scene import read_rows
from omniscs.errors import OmniscsError
from omniscs.preview import track_colour
from omniscs.scene.seen import captured, labelled
from omniscs.storage import atomic_write_bytes, atomic_write_json, atomic_write_text

CARD_JSON = "dataset.json"
CARD_MD = "README.md"
PREVIEW_PNG = "preview.png"
SCENES = "scenes"
BEV = "bev"
#: Contact sheet: tiles across and at most this many tiles.
PREVIEW_COLUMNS = 4
PREVIEW_TILES = 16
#: Width of one contact-sheet tile (pixels).
PREVIEW_TILE_WIDTH = 400


def link_tree(src: Path, dst: Path) -> None:
    """``dst`` as a copy of ``src`` made of hard links (a plain copy where the file system refuses links)."""
    for dirpath, _, filenames in os.walk(src):
        target = dst / Path(dirpath).relative_to(src)
        target.mkdir(parents=True, exist_ok=True)
        for name in filenames:
            try:
                os.link(Path(dirpath) / name, target / name)
            except OSError:
                shutil.copy2(Path(dirpath) / name, target / name)


def assemble_dataset(annotated: list[str | Path], out_dir: Path, final_dir: Path, dataset_id: str,
                     card_facts: dict, keep_failed: bool = False) -> dict:
    """Gather the annotate stages' outputs ``annotated`` into ``out_dir`` (a temporary folder that becomes
    ``final_dir``): variant stores, BEV pictures, preview and card. Variants that failed the quality gates
    (``omniscs.gates``) stay out unless ``keep_failed`` (then the card marks them); a run none of whose variants
    passed is an OmniscsError. Returns the card with the rows to catalogue (``samples``, ``annotations``,
    ``variants``: paths already pointing into ``final_dir``)."""
    samples, annotations, variants, judged = [], [], [], []
    for folder in annotated:
        folder = Path(folder)
        rows = read_rows(folder)
        judged.append(gate_record(rows))
        kept = {v["store_id"] for v in rows["variants"] if keep_failed or (v.get("gate") or {}).get("passed", True)}
        for v in rows["variants"]:
            if v["store_id"] not in kept:
                continue
            link_tree(folder / v["store_id"], out_dir / SCENES / v["store_id"])
            bev = folder / f"{v['store_id']}-bev.png"
            if bev.is_file():
                (out_dir / BEV).mkdir(exist_ok=True)
                link_tree_file(bev, out_dir / BEV / f"{v['store_id']}.png")
            variants.append(dict(v, path=str(final_dir / SCENES / v["store_id"])))
        for s in rows["samples"]:
            if s["store_id"] not in kept:
                continue
            store = final_dir / SCENES / s["store_id"]
            samples.append(dict(s, dataset_id=dataset_id, image_path=str(store / s["image_path"]),
                                gt_path=str(store / s["gt_path"])))
        annotations.extend(dict(a, dataset_id=dataset_id) for a in rows["annotations"] if a["store_id"] in kept)
    gates = gate_summary(judged, keep_failed)
    if not variants:
        if gates["rejected_total"]:
            raise OmniscsError(f"no variant passed the quality gates ({gates['rejected_total']} rejected: "
                               f"{first_reasons(gates)}); nothing is written. Raise --variant-budget to try more "
                               "candidates, relax the gates, or give --keep-failed to build the dataset from them")
        raise OmniscsError("no annotated variant to put in a dataset; ask for behaviour variants of at least one "
                           "scene with a vehicle besides the ego, or for appearance variants")
    lidar = lidar_coverage(store_boxes([out_dir / SCENES / v["store_id"] for v in variants]))
    card = dataset_card(dataset_id, variants, samples, annotations, card_facts, gates, lidar)
    atomic_write_json(out_dir / CARD_JSON, card)
    atomic_write_text(out_dir / CARD_MD, card_markdown(card))
    write_preview(out_dir, samples, annotations, out_dir / PREVIEW_PNG)
    return {"card": card, "samples": samples, "annotations": annotations, "variants": variants}


#: 2D box colours of an annotation in the preview (and the viewer's dataset view): an ordinary one, the adversary.
LABEL_COLOUR = (40, 220, 60)
ADVERSARY_LABEL_COLOUR = (230, 30, 30)
#: The variant levels a card counts, in order.
LEVELS = ("behaviour", "appearance", "designed")


def gate_record(rows: dict) -> dict:
    """One annotate stage's verdicts (its ``rows.json``): per variant its scene, level, whether it passed and why
    not, whether it was rendered; and what each level was asked for (``wanted``; None without gates)."""
    out = []
    for v in rows["variants"]:
        gate = v.get("gate") or {"passed": True, "reasons": []}
        out.append({"scene_id": v["scene_id"], "variant_id": str(v["variant_id"]), "level": v.get("level"),
                    "passed": bool(gate["passed"]), "reasons": list(gate["reasons"]), "rendered": True})
    scene = rows["variants"][0]["scene_id"] if rows["variants"] else None
    for r in rows.get("rejected") or []:
        out.append({"scene_id": r.get("scene_id", scene), "variant_id": str(r["variant_id"]), "level": r["level"],
                    "passed": False, "reasons": list(r["reasons"]), "rendered": False})
    return {"variants": out, "wanted": rows.get("wanted"), "spare": len(rows.get("spare") or [])}


def gate_summary(records: list[dict], keep_failed: bool) -> dict:
    """Requested, produced (passed) and rejected variants per level over a run's annotate stages, with every
    rejected variant's reasons."""
    requested = {level: 0 for level in LEVELS}
    produced = {level: 0 for level in LEVELS}
    rejected = {level: 0 for level in LEVELS}
    tried = {level: 0 for level in LEVELS}
    reasons = []
    for record in records:
        wanted = record["wanted"]
        for level in LEVELS:
            judged = [v for v in record["variants"] if v["level"] == level]
            requested[level] += len([v for v in judged if v["passed"]]) if wanted is None else int(wanted.get(level, 0))
        for v in record["variants"]:
            tried[v["level"]] += 1
            if v["passed"]:
                produced[v["level"]] += 1
            else:
                rejected[v["level"]] += 1
                reasons.append({k: v[k] for k in ("scene_id", "variant_id", "level", "reasons", "rendered")}
                               | {"in_dataset": bool(keep_failed and v["rendered"])})
    return {"requested": requested, "produced": produced, "rejected": rejected, "tried": tried,
            "rejected_total": sum(rejected.values()), "failed_kept": sum(r["in_dataset"] for r in reasons),
            "keep_failed": bool(keep_failed), "rejections": reasons}


def gate_counts(gates: dict) -> str:
    """The gates' counts as one line, per level asked for or tried (``gate_summary``'s requested/produced/rejected/
    tried): what ``dataset info`` and ``generate`` print."""
    n = {k: {level: gates[k].get(level, 0) for level in LEVELS} for k in ("requested", "produced", "rejected", "tried")}
    return "; ".join(f"{level} {n['produced'][level]} of {n['requested'][level]} requested passed, "
                     f"{n['rejected'][level]} rejected, {n['tried'][level]} tried"
                     for level in LEVELS if n["requested"][level] or n["tried"][level])


def first_reasons(gates: dict, n: int = 3) -> str:
    """The first ``n`` rejections as one line."""
    shown = [f"{r['variant_id']}: {'; '.join(r['reasons'])}" for r in gates["rejections"][:n]]
    more = len(gates["rejections"]) - n
    return " | ".join(shown) + (f" | and {more} more" if more > 0 else "")


def link_tree_file(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def _stats(values: list[float]) -> dict | None:
    v = [float(x) for x in values if x is not None and np.isfinite(x)]
    if not v:
        return None
    return {"mean": float(np.mean(v)), "median": float(np.median(v)), "min": float(np.min(v)),
            "max": float(np.max(v)), "n": len(v)}


#: Boxes nearer than this to the ego (metres) are the ones the LiDAR share is reported for (nuScenes evaluates
#: detection up to 50 m).
LIDAR_RANGE_M = 50.0
#: Below this share of boxes with LiDAR points (within LIDAR_RANGE_M) the card warns.
LIDAR_SHARE_WARNING = 0.9


def store_boxes(stores: list[str | Path]) -> list[dict]:
    """Every box of the variant ``stores`` (every frame and track, those no camera sees included): store, frame,
    track, LiDAR points, visible pixels and horizontal distance of its centre from the ego (metres)."""
    from omniscs.scene import load_scene

    out = []
    for path in stores:
        scene = load_scene(path)
        b = scene.boxes
        if len(b) == 0:
            continue
        ego = scene.world_from_ego_all[b.frame_idx.to_numpy(np.int64)]  # [N, 4, 4]
        dist = np.hypot(b.cx.to_numpy() - ego[:, 0, 3], b.cy.to_numpy() - ego[:, 1, 3])
        out += [{"store_id": scene.scene_id, "frame_idx": int(f), "track_id": int(t), "num_lidar_points": int(n),
                 "visible_pixels": int(v), "distance_m": float(d)}
                for f, t, n, v, d in zip(b.frame_idx, b.track_id, b.num_lidar_points, b.visible_pixels, dist)]
    return out


def lidar_coverage(boxes: list[dict], max_range_m: float = LIDAR_RANGE_M) -> dict:
    """Of ``boxes`` (``store_boxes``), those with and without LiDAR points, all and within ``max_range_m`` of the
    ego, counted over the boxes the exports label (``omniscs.scene.seen``: per track, from the first box a sensor
    captured, by LiDAR points or visible pixels, to the last); ``unlabelled`` counts the others (hidden from every
    sensor before, after or throughout a track). A box whose points were not measured (-1) is left out."""
    measured = {(b["store_id"], b["frame_idx"], b["track_id"]): b for b in boxes if b["num_lidar_points"] >= 0}
    keep = labelled((key, key[::2], key[1], captured(b["num_lidar_points"], b["visible_pixels"]))
                    for key, b in measured.items())
    kept = [(b["num_lidar_points"], b["distance_m"]) for key, b in measured.items() if key in keep]
    near = [n for n, d in kept if d <= max_range_m]
    return {"boxes": len(kept), "with_points": sum(n > 0 for n, _ in kept), "unlabelled": len(measured) - len(kept),
            "within_m": max_range_m, "boxes_within": len(near), "with_points_within": sum(n > 0 for n in near),
            "share_within": (sum(n > 0 for n in near) / len(near)) if near else None}


def card_warnings(counts: dict, gates: dict, lidar: dict, failed_scenes: list[dict] = ()) -> list[str]:
    """What a user must know before training on the dataset, in plain words."""
    out = [f"scene {f['scene']} failed and is not in the dataset: {f['error']}" for f in failed_scenes]
    for level in LEVELS:
        asked, made, tried = (gates[k].get(level, 0) for k in ("requested", "produced", "tried"))
        if asked and made < asked:
            out.append(f"{made} of {asked} requested {level} variant(s) passed the quality gates ({tried} tried)")
    behaviour = [r for r in gates["rejections"] if r["level"] == "behaviour"]
    if gates["requested"]["behaviour"] and gates["produced"]["behaviour"] == 0 and behaviour:
        collided = sum(not any(t.startswith(("no collision", "neither a collision")) for t in r["reasons"])
                       for r in behaviour)
        out.append(f"{collided} of {len(behaviour)} behaviour variant(s) reached a collision")
    if gates["failed_kept"]:
        out.append(f"{gates['failed_kept']} variant(s) in this dataset failed the quality gates (kept on request; "
                   "passed_gates false in the card and the variants table)")
    if lidar["share_within"] is not None and lidar["share_within"] < LIDAR_SHARE_WARNING:
        out.append(f"only {lidar['with_points_within']} of {lidar['boxes_within']} boxes within "
                   f"{lidar['within_m']:g} m have LiDAR points; nuScenes' evaluation and UniAD's valid_flag drop "
                   "the others")
    if counts["dropped_frames"]:
        out.append(f"{counts['dropped_frames']} frame(s) were not rendered: the ego left the fitted area")
    return out


def dataset_card(dataset_id: str, variants: list[dict], samples: list[dict], annotations: list[dict],
                 facts: dict, gates: dict | None = None, lidar: dict | None = None) -> dict:
    """The dataset card: what was asked for, what went in and what was rejected (with reasons), how faithful the
    renders are, how many boxes the LiDAR sees, and warnings in plain words."""
    gates = gates or gate_summary([], False)
    categories: dict[str, int] = {}
    levels = {1: 0, 2: 0, 3: 0, 4: 0}
    for a in annotations:
        categories[a["category"]] = categories.get(a["category"], 0) + 1
        levels[int(a["visibility_level"])] += 1
    commands: dict[str, int] = {}
    for s in samples:
        commands[s["command"]] = commands.get(s["command"], 0) + 1
    counts = {"scenes": len({v["scene_id"] for v in variants}), "variants": len(variants),
              "frames": int(sum(v["n_frames"] for v in variants)), "images": len(samples),
              "annotations": len(annotations),
              "ego_solved": sum(bool(v.get("ego_solved")) for v in variants),
              "variants_by_level": {level: sum(v.get("level", "behaviour") == level for v in variants)
                                    for level in LEVELS},
              "dropped_frames": int(sum(v["dropped_frames"] for v in variants)),
              "annotations_by_category": dict(sorted(categories.items())),
              "annotations_by_visibility": {f"level {k}": n for k, n in levels.items()},
              "samples_by_command": dict(sorted(commands.items()))}
    lidar = lidar if lidar is not None else lidar_coverage([])
    return {
        "dataset_id": dataset_id, **facts,
        "counts": counts,
        "gates": gates,
        "lidar": lidar,
        "warnings": card_warnings(counts, gates, lidar, facts.get("failed_scenes") or []),
        "fidelity": {"variant_psnr": _stats([v.get("fidelity_psnr") for v in variants]),
                     "variant_ssim": _stats([v.get("fidelity_ssim") for v in variants]),
                     "variant_masked_psnr": _stats([v.get("fidelity_masked_psnr") for v in variants]),
                     "variant_feature_drift": _stats([v.get("feature_drift") for v in variants]),
                     "variant_logged_psnr": _stats([v.get("logged_psnr") for v in variants]),
                     "max_viewpoint_offset_m": _stats([v.get("max_viewpoint_offset_m") for v in variants])},
        "variants": [{**{k: v.get(k) for k in ("scene_id", "variant_id", "store_id", "level", "n_frames", "n_images",
                                               "n_annotations", "dropped_frames", "ego_solved", "fidelity_psnr",
                                               "fidelity_ssim", "fidelity_masked_psnr", "feature_drift",
                                               "max_viewpoint_offset_m")},
                      "passed_gates": (v.get("gate") or {}).get("passed", True)}
                     for v in variants],
    }


def card_markdown(card: dict) -> str:
    c, fid = card["counts"], card["fidelity"]
    gates = card.get("gates") or gate_summary([], False)
    lidar = card.get("lidar")

    def stat(s: dict | None, unit: str = "") -> str:
        return "not measured" if s is None else f"mean {s['mean']:.2f}{unit}, median {s['median']:.2f}{unit}, " \
                                                f"min {s['min']:.2f}{unit}, max {s['max']:.2f}{unit} over {s['n']} " \
                                                "variant(s)"

    lines = [f"# Dataset {card['dataset_id']}", ""]
    if card.get("warnings"):
        lines += ["**Warnings**", ""] + [f"- {w}" for w in card["warnings"]] + [""]
    designed = c['variants_by_level'].get('designed', 0)
    lines += [f"{c['variants']} SCS variant(s) of {c['scenes']} scene(s) ({c['variants_by_level']['behaviour']} "
              f"behaviour-level, {c['variants_by_level']['appearance']} appearance-level"
              + (f", {designed} designed" if designed else "") + f"): {c['frames']} frames, "
              f"{c['images']} annotated images, {c['annotations']} box annotations (one per box and camera).", "",
              f"- Sources: {', '.join(card.get('sources') or []) or 'n/a'}",
              f"- The ego drives its avoiding solution in {c['ego_solved']} of "
              f"{c['variants_by_level']['behaviour']} behaviour variant(s) in the dataset. Appearance and designed "
              "variants keep the logged ego.",
              f"- Frames not rendered because the ego left the fitted area: {c['dropped_frames']}",
              f"- Fidelity against the exact render (procedural scenes): PSNR {stat(fid['variant_psnr'], ' dB')}; "
              f"SSIM {stat(fid['variant_ssim'])}; on agents, PSNR {stat(fid['variant_masked_psnr'], ' dB')}",
              f"- Distance of the rendered ego from the logged path: {stat(fid['max_viewpoint_offset_m'], ' m')}",
              "- Feature drift against the unedited render of the logged view, edited agents left out (0 = same "
              f"structure; the proxy for recorded logs): {stat(fid.get('variant_feature_drift'))}; the unedited "
              f"render against the logged images: PSNR {stat(fid.get('variant_logged_psnr'), ' dB')}"]
    if lidar is not None:
        share = "n/a" if lidar["share_within"] is None else f"{100 * lidar['share_within']:.0f} %"
        lines.append(f"- Boxes with LiDAR points: {lidar['with_points']} of {lidar['boxes']}; within "
                     f"{lidar['within_m']:g} m of the ego {lidar['with_points_within']} of {lidar['boxes_within']} "
                     f"({share}); {lidar.get('unlabelled', 0)} box(es) no sensor captures before, after or "
                     "throughout their track are not labelled (nuScenes' rule; exports leave them out)")
    lines += [f"- Annotations by category: {c['annotations_by_category']}",
              f"- Annotations by nuScenes visibility level: {c['annotations_by_visibility']}",
              f"- Samples by driving command: {c['samples_by_command']}", "",
              "## Quality gates", "",
              "| level | requested | passed | rejected | tried |", "|---|---:|---:|---:|---:|"]
    for level in LEVELS:
        n = [gates[k].get(level, 0) for k in ("requested", "produced", "rejected", "tried")]
        if level != "designed" or any(n):  # a designed variant only when the request had edits
            lines.append(f"| {level} | {' | '.join(map(str, n))} |")
    lines.append("")
    if gates["rejections"]:
        where = "in the dataset, marked" if gates["keep_failed"] else "kept in the workspace and the catalog only"
        lines += [f"Rejected variants ({where}):", ""]
        lines += [f"- {r['scene_id']} {r['variant_id']} ({r['level']}{'' if r['rendered'] else ', not rendered'}"
                  f"{', in the dataset' if r['in_dataset'] else ''}): {'; '.join(r['reasons'])}"
                  for r in gates["rejections"]]
        lines.append("")
    lines += ["## Config", "", "```json", json.dumps(card.get("config"), indent=2, sort_keys=True), "```", "",
              "## Variants", "", "| scene | variant | level | passed gates | frames | images | boxes | ego solved "
              "| PSNR dB | masked PSNR dB | drift |", "|---|---|---|---|---:|---:|---:|---|---:|---:|---:|"]
    for v in card["variants"]:
        def num(x, digits=2):
            return "" if x is None else f"{x:.{digits}f}"
        lines.append(f"| {v['scene_id']} | {v['variant_id']} | {v.get('level') or ''} | "
                     f"{v.get('passed_gates', True)} | {v['n_frames']} | {v['n_images']} | "
                     f"{v['n_annotations']} | {v['ego_solved']} | {num(v['fidelity_psnr'])} | "
                     f"{num(v['fidelity_masked_psnr'])} | {num(v.get('feature_drift'), 3)} |")
    return "\n".join(lines) + "\n"


def _colour(track_id: int) -> tuple[int, int, int]:
    return tuple(int(c) for c in track_colour(int(track_id)))


def write_preview(root: Path, samples: list[dict], annotations: list[dict], out_png: Path) -> Path:
    """Contact sheet: up to PREVIEW_TILES rendered images spread over the variants and frames, each with its
    instance masks tinted and its boxes drawn (projected 3D box; red = the adversary)."""
    if not samples:
        raise OmniscsError("no sample to preview")
    by_image: dict[tuple, list[dict]] = {}
    for a in annotations:
        by_image.setdefault((a["store_id"], a["frame_idx"], a["camera"]), []).append(a)
    pick = np.unique(np.linspace(0, len(samples) - 1, min(PREVIEW_TILES, len(samples))).round().astype(int))
    tiles = []
    for i in pick:
        s = samples[i]
        store = root / SCENES / s["store_id"]
        rgb = cv2.cvtColor(cv2.imread(str(store / "images" / s["camera"] / f"{s['frame_idx']:06d}.png")),
                           cv2.COLOR_BGR2RGB)
        with np.load(store / "gt" / s["camera"] / f"{s['frame_idx']:06d}.npz") as gt:
            instance = gt["instance"]
        tint = rgb.astype(np.float32)
        for tid in np.unique(instance[instance >= 0]):
            m = instance == tid
            tint[m] = 0.55 * tint[m] + 0.45 * np.array(_colour(tid), np.float32)
        img = tint.clip(0, 255).astype(np.uint8)
        scale = PREVIEW_TILE_WIDTH / img.shape[1]
        img = cv2.resize(img, (PREVIEW_TILE_WIDTH, max(1, int(round(img.shape[0] * scale)))),
                         interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_NEAREST)
        for a in by_image.get((s["store_id"], s["frame_idx"], s["camera"]), []):
            colour = ADVERSARY_LABEL_COLOUR if a["is_adversary"] else LABEL_COLOUR
            p1 = (int(a["x1"] * scale), int(a["y1"] * scale))
            p2 = (int(a["x2"] * scale) - 1, int(a["y2"] * scale) - 1)
            cv2.rectangle(img, p1, p2, colour, 1)
            cv2.putText(img, f"{a['track_id']} v{a['visibility_level']}", (p1[0] + 2, p1[1] + 11),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.35, colour, 1, cv2.LINE_AA)
        caption = f"{s['store_id']} f{s['frame_idx']} {s['camera']} {s['command']}"
        cv2.rectangle(img, (0, 0), (img.shape[1], 14), (0, 0, 0), -1)
        cv2.putText(img, caption, (3, 10), cv2.FONT_HERSHEY_SIMPLEX, 0.33, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(img)
    h = max(t.shape[0] for t in tiles)
    tiles = [np.pad(t, ((0, h - t.shape[0]), (0, 0), (0, 0))) for t in tiles]
    while len(tiles) % PREVIEW_COLUMNS and len(tiles) > PREVIEW_COLUMNS:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[i:i + PREVIEW_COLUMNS], 1) for i in range(0, len(tiles), PREVIEW_COLUMNS)]
    sheet = np.concatenate(rows, 0)
    ok, png = cv2.imencode(".png", cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    if not ok:
        raise OmniscsError(f"could not encode {out_png}")
    return atomic_write_bytes(out_png, png.tobytes())
