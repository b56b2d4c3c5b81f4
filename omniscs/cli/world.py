"""``omniscs world``: procedural driving worlds (the embedded synthetic default input)."""
from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from omniscs.checks import MAX_SEED
from omniscs.errors import OmniscsError

from omniscs.cli.common import check_out, console, depth_picture, progress_bars, read_edits

app = typer.Typer(help="Procedural driving worlds (the embedded synthetic default input).", no_args_is_help=True)


@app.command("make")
def world_make(
    out: Path = typer.Option(..., help="Directory to write the scene store to (must not exist)."),
    template: str = typer.Option("straight", help="Road layout template."),
    seed: int = typer.Option(0, min=0, max=MAX_SEED, help="Seed for layout, assets and traffic."),
    frames: int = typer.Option(40, help="Frames at 10 Hz."),
    cameras: int = typer.Option(3, help="Cameras, 1 to 6, nuScenes-like placement."),
    width: int = typer.Option(480), height: int = typer.Option(270),
    lighting: str = typer.Option("day", help="day, dusk, night or fog."),
    overwrite: bool = typer.Option(False, help="Replace an existing scene store at --out."),
) -> None:
    """Generate a procedural driving log and render it into a scene store with exact ground truth."""
    from omniscs.scene import SyntheticSource, check_synthetic, load_scene
    from omniscs.scene.synthetic import write_synthetic_scene

    source = SyntheticSource(template, seed, lighting, frames, cameras, width, height)
    check_synthetic(source)
    check_out(out, overwrite)
    started = time.perf_counter()
    with progress_bars() as bars:
        write_synthetic_scene(source, out, overwrite=overwrite, progress=bars.sink(f"render {source.scene_id()}"))
    scene = load_scene(out)
    console.print(f"wrote {scene} to {out} in {time.perf_counter() - started:.1f} s")


@app.command("render")
def world_render(
    scene_path: Path = typer.Argument(..., help="A synthetic scene store (it keeps the world it came from)."),
    out: Path = typer.Option(..., help="PNG to write."),
    camera: str = typer.Option("CAM_FRONT"), frame: int = typer.Option(0),
    edit: Optional[str] = typer.Option(None, help="Edit list as JSON, or @file.json (see README)."),
    masks: bool = typer.Option(False, help="Append the instance mask and depth beside the image."),
) -> None:
    """Ground truth for an edit: re-render a synthetic scene's world with edits applied."""
    import cv2
    import numpy as np

    from omniscs.preview import track_colour
    from omniscs.scene import load_scene
    from omniscs.storage import atomic_write_bytes
    from omniscs.world import WorldRenderer, apply_edits

    scene = load_scene(scene_path)
    if scene.world is None:
        raise OmniscsError(f"{scene_path} is not a synthetic scene (no world.json); only those can be re-rendered")
    check_out(out, overwrite=True, suffix=".png")
    world = apply_edits(scene.world, read_edits(edit))
    scene.camera(camera)
    scene.check_frame(frame)
    r = WorldRenderer(world).render_camera(frame, camera)
    tiles = [r.rgb]
    if masks:
        ids = np.unique(r.instance[r.instance >= 0])
        inst = np.zeros_like(r.rgb)
        for tid in ids:
            inst[r.instance == tid] = track_colour(int(tid))
        d = depth_picture(r.depth)
        turbo = cv2.applyColorMap(d, cv2.COLORMAP_TURBO)[..., ::-1].copy()
        turbo[d == 0] = 0
        tiles += [inst, turbo]
    ok, png = cv2.imencode(".png", cv2.cvtColor(np.concatenate(tiles, axis=1), cv2.COLOR_RGB2BGR))
    atomic_write_bytes(out, png.tobytes())
    console.print(f"wrote {out}")


@app.command("export")
def world_export(
    scenes: list[Path] = typer.Argument(..., help="Scene stores to export (one dataset holds them all)."),
    fmt: str = typer.Option(..., "--format", help="nuscenes, kitti, waymo-v2, uniad (nuScenes + UniAD infos) or "
                                                  "openscenario (.xosc + .xodr)."),
    out: Path = typer.Option(..., help="Dataset root to write (must not exist)."),
    version: str = typer.Option("v1.0-trainval", help="nuScenes: table version folder (the one every export writes "
                                                      "unless told; eval and predict read a dataroot's only one)."),
    keyframe_every: Optional[int] = typer.Option(None, help="nuScenes: frames per keyframe (default: 2 Hz)."),
    camera: str = typer.Option("CAM_FRONT", help="KITTI: the camera written as image_02."),
    keep_unseen: bool = typer.Option(False, help="nuScenes, uniad: also label boxes no sensor captured (no LiDAR "
                                                 "point, no visible pixel) before an object is first seen or after "
                                                 "it is last seen, and objects never seen."),
    overwrite: bool = typer.Option(False, help="Replace an existing dataset at --out."),
) -> None:
    """Write scene stores as a nuScenes v1.0, KITTI tracking or Waymo Open Dataset v2 dataset, or as OpenSCENARIO
    scenarios on OpenDRIVE roads."""
    from omniscs.export import WRITERS, export_scenes

    if fmt not in WRITERS:
        raise OmniscsError(f"unknown --format {fmt!r}; use one of {list(WRITERS)}")
    check_out(out, overwrite)
    nuscenes = {"version": version, "keyframe_every": keyframe_every, "keep_unseen": keep_unseen}
    options = {"nuscenes": nuscenes, "kitti": {"camera": camera}, "waymo-v2": {}, "uniad": nuscenes,
               "openscenario": {}}[fmt]
    if keep_unseen and fmt not in ("nuscenes", "uniad"):
        raise OmniscsError("--keep-unseen applies to --format nuscenes and uniad only")
    started = time.perf_counter()
    with progress_bars() as bars:
        export_scenes(scenes, fmt, out, overwrite=overwrite, progress=bars.sink(f"export {fmt}"), **options)
    console.print(f"wrote {len(scenes)} scene(s) as {fmt} to {out} in {time.perf_counter() - started:.1f} s")
