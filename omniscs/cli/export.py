"""``omniscs export``: a fitted (and edited) scene graph as files other tools open."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from omniscs.cli.common import check_out, console, edited_graph, read_edits

app = typer.Typer(help="Export a fitted scene graph for other tools (3D Gaussian splatting PLY).",
                  no_args_is_help=True)


@app.command("ply")
def export_ply(
    checkpoint: Path = typer.Argument(..., help="A scene-graph checkpoint folder (omniscs fit --out, or a stage's)."),
    out: Path = typer.Option(..., help="The PLY file to write (with --split: a folder of PLY files)."),
    frame: int = typer.Option(0, help="The frame whose agent poses place the agents."),
    edit: Optional[str] = typer.Option(None, help="Edit list as JSON, or @file.json (see README), applied first."),
    pool: Optional[Path] = typer.Option(None, help="Model pool whose model ids (pm-...) the edits may name."),
    split: bool = typer.Option(False, help="One file per node: background.ply and agent-<track>.ply."),
    overwrite: bool = typer.Option(False, help="Replace an existing --out (a folder only if omniscs wrote it)."),
) -> None:
    """Write the scene graph at one frame as standard 3DGS PLY (the INRIA layout: SuperSplat, viser and the original
    viewer open it): the background and every agent present at --frame, placed at its pose there."""
    from omniscs.errors import OmniscsError
    from omniscs.nsg.checkpoint import load_graph
    from omniscs.nsg.splat_export import write_scene_ply

    check_out(out, overwrite, suffix=None if split else ".ply")
    edits = read_edits(edit)
    graph = edited_graph(load_graph(checkpoint), edits, pool)
    if not 0 <= frame < graph.n_frames:
        raise OmniscsError(f"--frame {frame} is out of range: {graph.scene_id} has frames 0 to {graph.n_frames - 1}")
    files = write_scene_ply(graph, frame, out, split=split, overwrite=overwrite)
    agents = [a for a in graph.agents if a.present[frame] and len(a.gaussians)]
    n = len(graph.background) + sum(len(a.gaussians) for a in agents)
    console.print(f"wrote {out} ({graph.scene_id}, frame {frame}, {len(agents)} agent(s), {n:,} Gaussians in "
                  f"{len(files)} file(s), {len(edits)} edit(s))")
