"""``omniscs scene`` (inspect scene stores) and ``omniscs ingest`` (recorded datasets into scene stores)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from omniscs.cli.common import comma_list, console, print_error, print_table, progress_bars
from omniscs.errors import OmniscsError
from omniscs.storage import check_output

app = typer.Typer(help="Inspect scene stores.", no_args_is_help=True)


def ingest(
    source: str = typer.Option(..., "--source", help="Dataset format: nuscenes, kitti or waymo-v2."),
    dataroot: Path = typer.Option(..., help="nuScenes root (holds v1.0-*/), KITTI tracking root, Waymo v2 split folder."),
    out: Path = typer.Option(..., help="Folder for the scene stores (one sub-folder per scene)."),
    scenes: Optional[list[str]] = typer.Option(None, "--scenes", help="Scenes / sequences / segments to read "
                                               "(repeat or comma-separate; default: all)."),
    version: Optional[str] = typer.Option(None, help="nuScenes table version (default: the only one); KITTI split."),
    sweeps: bool = typer.Option(False, help="nuScenes: every LiDAR sweep (annotations interpolated), not only keyframes."),
    cameras: Optional[str] = typer.Option(None, help="Comma-separated cameras to keep (default: all)."),
    skip_bad_frames: bool = typer.Option(False, "--skip-bad-frames",
                                         help="Leave unreadable frames out with a warning instead of failing."),
    overwrite: bool = typer.Option(False, help="Read scenes again even when an up-to-date store exists."),
) -> None:
    """Read scenes of a recorded dataset into validated scene stores."""
    import warnings

    from omniscs.pipeline.stages import ingest_stage
    from omniscs.scene import DatasetSource, load_scene
    from omniscs.scene.sources import FORMATS, SkippedFramesWarning, list_scenes

    if source not in FORMATS:
        raise OmniscsError(f"unknown --source {source!r}; use one of {list(FORMATS)}")
    out = check_output(out, follow=True)
    if not dataroot.is_dir():
        raise OmniscsError(f"--dataroot {dataroot} is not a directory")
    names = [n for item in (scenes or []) for n in comma_list(item)] or list_scenes(source, dataroot, version)
    if not names:
        raise OmniscsError(f"{dataroot} holds no {source} scene")
    cams = comma_list(cameras) or None
    rows = []
    with progress_bars() as bars:
        for name in names:
            src = DatasetSource(source, str(dataroot.resolve()), name, version=version, cameras=cams, sweeps=sweeps,
                                skip_bad_frames=skip_bad_frames)
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", SkippedFramesWarning)
                record = ingest_stage(src, out, progress=bars.sink(f"{source} {name}"), scenes_root=out,
                                      reuse=not overwrite)
            for w in caught:
                print_error(str(w.message), "warning", "yellow")
            scene = load_scene(record.path)
            rows.append({"scene": name, "scene_id": scene.scene_id, "frames": scene.n_frames,
                         "boxes": len(scene.boxes), "skipped": len(scene.manifest.get("skipped_frames", [])),
                         "reused": record.reused, "seconds": record.seconds, "path": record.path})
    print_table(rows, title=f"{source} {dataroot}")


@app.command("info")
def scene_info(path: Path, as_json: bool = typer.Option(False, "--json", help="Print JSON."),
               verify: bool = typer.Option(True, help="Check every file against its recorded hash and every image's "
                                                      "structure first (about 0.05 s per 100 images; --no-verify "
                                                      "reads only the tables).")) -> None:
    """Summarise a scene store: source, frames, cameras, tracks."""
    from omniscs.scene import load_scene
    from omniscs.scene.store import verify_store
    from omniscs.scene.summary import agent_rows

    scene = verify_store(path) if verify else load_scene(path)
    agents = agent_rows(scene)
    info = {
        "scene_id": scene.scene_id, "path": str(scene.path), "source": scene.source,
        "n_frames": scene.n_frames,
        "duration_s": float((scene.frames.timestamp_us.iloc[-1] - scene.frames.timestamp_us.iloc[0]) * 1e-6),
        "cameras": {c: {"size": list(scene.image_size(c))} for c in scene.camera_names},
        "has_lidar": scene.has_lidar, "has_gt": scene.has_gt, "content_hash": scene.content_hash,
        "n_tracks": len(agents), "n_moving": sum(a["moving"] for a in agents),
        "tracks": [{k: a[k] for k in ("track_id", "category", "n_frames", "path_length_m", "moving",
                                      "max_visible_pixels", "min_distance_to_ego_m")} for a in agents],
    }
    if as_json:
        typer.echo(json.dumps(info, indent=2, default=str))
        return
    console.print(f"{info['scene_id']}  {info['path']}")
    console.print(f"source: {json.dumps(info['source'])}")
    console.print(f"{info['n_frames']} frames over {info['duration_s']:.1f} s; cameras: "
                  + ", ".join(f"{c} {v['size'][0]}x{v['size'][1]}" for c, v in info["cameras"].items()))
    console.print(f"LiDAR: {info['has_lidar']}; ground truth: {info['has_gt']}; "
                  f"{info['n_tracks']} tracks ({info['n_moving']} moving)")
    print_table(info["tracks"], title="tracks")


@app.command("preview")
def scene_preview(path: Path, out: Optional[Path] = typer.Option(None, help="Folder for the PNGs (default: PATH/preview).")) -> None:
    """Write a contact sheet (cameras over time, boxes projected) and a bird's-eye trajectory plot."""
    from omniscs.preview import write_previews
    from omniscs.scene import load_scene

    scene = load_scene(path)
    paths = write_previews(scene, out or Path(path) / "preview")
    for name, p in paths.items():
        console.print(f"{name}: {p}")
