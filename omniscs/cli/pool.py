"""``omniscs pool import / export / list``: the model pool of 360-degree road-user models (``omniscs.agents.pool``)."""
from __future__ import annotations

import json
from pathlib import Path

import typer

from omniscs.cli.common import console

app = typer.Typer(help="The model pool: 360-degree Gaussian models of road users in their vehicle frame.",
                  no_args_is_help=True)
POOL = typer.Option(..., "--pool", help="The pool folder (created on the first import).")


@app.command("import")
def pool_import(
    file: Path = typer.Argument(..., help="A 3D Gaussian splatting PLY (x, y, z, f_dc_*, f_rest_*, opacity, "
                                          "scale_*, rot_*), e.g. an image-to-3D generator's output."),
    category: str = typer.Option(..., help="Its category (car, truck, bus, trailer, pedestrian, ...)."),
    pool: Path = POOL,
    no_calibrate: bool = typer.Option(False, "--no-calibrate", help="Take the model's frame as it is (already +x "
                                                                    "heading, z up, box-centred)."),
) -> None:
    """Import a splat file into the pool (turned into its vehicle frame); prints the model id on its last line."""
    from omniscs.agents.pool import Pool

    p = Pool(pool)
    model_id = p.import_ply(file, category, calibrate=not no_calibrate)
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

    console.print(f"wrote {Pool(pool).export_ply(model_id, out)}")


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
    for aid in ids:
        row = pool_asset_stage(aid, out, gaussians, refine_steps).rows["pool"][0]
        quality = "n/a" if row["quality"] is None else f"{row['quality']:.1f} dB"
        console.print(f"{row['model_id']}  {aid:<18} {row['category']:<22} {quality}  {row['seconds']:.1f} s"
                      + ("" if row["new"] else "  (already in the pool)"))
