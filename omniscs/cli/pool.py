"""``omniscs pool import / export / remove / list``: the model pool of 360-degree road-user models
(``omniscs.agents.pool``)."""
from __future__ import annotations

import json
from pathlib import Path

import typer

from omniscs.cli.common import console
from omniscs.storage import check_output

app = typer.Typer(help="The model pool: 360-degree Gaussian models of road users in their vehicle frame.",
                  no_args_is_help=True)
POOL = typer.Option(..., "--pool", help="The pool folder (created on the first import).")


@app.command("import")
def pool_import(
    file: Path = typer.Argument(..., help="A 3D Gaussian splatting PLY (x, y, z, f_dc_*, f_rest_*, opacity, "
                                          "scale_*, rot_*), e.g. an image-to-3D generator's output, or a mesh "
                                          "(OBJ, GLB/glTF, PLY, STL, OFF) made into Gaussians."),
    category: str = typer.Option(..., help="Its category (car, truck, bus, trailer, pedestrian, ...)."),
    pool: Path = POOL,
    no_calibrate: bool = typer.Option(False, "--no-calibrate", help="Take the model's frame as it is (already +x "
                                                                    "heading, z up, box-centred)."),
) -> None:
    """Import a splat file or a mesh into the pool (turned into its vehicle frame); prints the model id on its last
    line."""
    from omniscs.agents.pool import Pool

    p = Pool(pool)
    model_id = p.import_file(file, category, calibrate=not no_calibrate)
    meta = p.get(model_id).meta
    size = " x ".join(f"{v:.2f}" for v in meta["size"])
    console.print(f"{meta['n_gaussians']} Gaussians, {size} m, calibration: "
                  f"{(meta.get('calibration') or {}).get('heading_by', 'none')}")
    print(model_id)


@app.command("export")
def pool_export(model_id: str = typer.Argument(..., help="A pool model id (pm-...)."),
                out: Path = typer.Option(..., help="The PLY file to write."), pool: Path = POOL) -> None:
    """Write a pool model as a 3D Gaussian splatting PLY (opens in common splat viewers)."""
    from omniscs.agents.pool import Pool

    console.print(f"wrote {Pool(pool).export_ply(model_id, check_output(out))}")


@app.command("remove")
def pool_remove(model_id: str = typer.Argument(..., help="A pool model id (pm-...)."), pool: Path = POOL) -> None:
    """Take a model out of the pool (its index row, then its files). The catalog's ``pool`` table keeps the record of
    its addition; ``omniscs pool list`` shows what the pool holds now."""
    from omniscs.agents.pool import Pool

    meta = Pool(pool).remove(model_id)
    console.print(f"removed {model_id} ({meta.get('category', '?')}, from {meta.get('source', '?')}) from {pool}")


@app.command("list")
def pool_list(pool: Path = typer.Argument(..., help="The pool folder."),
              as_json: bool = typer.Option(False, "--json", help="One JSON object per model, one per line.")) -> None:
    """The pool's models: id, category, size, Gaussians, provenance, source, quality."""
    from omniscs.agents.pool import Pool

    table = Pool(pool).table()
    if as_json:
        for row in table.to_dict("records"):
            print(json.dumps(row, default=str))
        return
    from rich.table import Table

    t = Table(title=f"pool {pool}: {len(table)} model(s)")
    for col in ("model_id", "category", "length", "width", "height", "n_gaussians", "provenance", "source"):
        t.add_column(col)
    for row in table.itertuples():
        t.add_row(row.model_id, row.category, f"{row.length:.2f}", f"{row.width:.2f}", f"{row.height:.2f}",
                  str(row.n_gaussians), row.provenance, row.source)
    console.print(t)


@app.command("build")
def pool_build(
    assets: str = typer.Option(..., help="Asset ids or kinds of the world's asset library, comma-separated "
                                         "(e.g. sedan-0003,bus or sedan)."),
    out: Path = typer.Option(..., help="The pool folder (created or added to)."),
    gaussians: int = typer.Option(20_000, help="Gaussians per model."),
    refine_steps: int = typer.Option(100, help="Refinement steps against ray-cast views (0: none)."),
) -> None:
    """Pool models from the asset library's meshes (Gaussians on the surface, refined against ray-cast views,
    scored on held-out views); prints one line per model and the seconds each took."""
    from omniscs.errors import ValidationError
    from omniscs.pipeline.pool import asset_ids, pool_asset_stage

    ids = asset_ids(assets.split(","))
    if gaussians < 10 or refine_steps < 0:
        raise ValidationError("--gaussians must be >= 10 and --refine-steps >= 0")
    out = check_output(out, follow=True)
    for aid in ids:
        row = pool_asset_stage(aid, out, gaussians, refine_steps).rows["pool"][0]
        quality = "n/a" if row["quality"] is None else f"{row['quality']:.1f} dB"
        console.print(f"{row['model_id']}  {aid:<18} {row['category']:<22} {quality}  {row['seconds']:.1f} s"
                      + ("" if row["new"] else "  (already in the pool)"))


@app.command("match")
def pool_match(
    scene_path: Path = typer.Argument(..., help="A scene store."),
    pool: Path = POOL,
    tracks: str = typer.Option("", help="Track ids, comma-separated (default: every vehicle track)."),
    views: int = typer.Option(4, help="Largest views per track used as its query crops."),
) -> None:
    """Each track's pool model (Hungarian over appearance and box shape, within its category): JSON
    {track: {model_id, distance, category}}; tracks without a view or a model of their category map to null."""
    from omniscs.agents.dual import DualConfig, scene_query_views, track_views
    from omniscs.agents.matching import match_tracks
    from omniscs.agents.pool import Pool
    from omniscs.cli.common import comma_list
    from omniscs.errors import ValidationError
    from omniscs.nsg.agent import track_poses
    from omniscs.scene import load_scene
    from omniscs.taxonomy import VEHICLE_CATEGORIES

    if not pool.is_dir():
        raise ValidationError(f"--pool {pool} is not a pool folder")
    scene = load_scene(scene_path)
    boxes = scene.boxes
    ids = comma_list(tracks, int, "--tracks", "1,2") if tracks.strip() else sorted(
        int(t) for t in boxes[boxes.category.isin(VEHICLE_CATEGORIES)].track_id.unique())
    unknown = sorted(set(ids) - set(int(t) for t in boxes.track_id.unique()))
    if unknown:
        raise ValidationError(f"scene {scene.scene_id} has no track(s) {unknown}")
    config = DualConfig()
    frames = range(scene.n_frames)
    queries, scales, sizes, cats = {}, {}, {}, {}
    for t in ids:
        queries[t], scales[t] = scene_query_views(scene, t, track_views(scene, t, frames, config.min_view_pixels),
                                                  views)
        sizes[t] = track_poses(boxes, t, scene.n_frames)[2]
        cats[t] = str(boxes[boxes.track_id == t].category.iloc[0])
    matches = match_tracks(queries, sizes, cats, Pool(pool), size_weight=config.size_weight, scales=scales)
    print(json.dumps({str(t): ({"model_id": matches[t][0], "distance": round(matches[t][1], 4), "category": cats[t]}
                               if t in matches else None) for t in ids}, indent=1))
