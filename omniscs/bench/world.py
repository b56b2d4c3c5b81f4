"""Benchmark of the procedural world: generate a log and render every camera and LiDAR sweep of it.

Writes ``reports/world/report.json``, ``report.md``, a per-frame timing plot ``report.png`` and a
preview of the first frame's cameras ``preview.png``; also times open3d against embreex
on the same camera rays (a ratio from one run, since the machines are shared and noisy).
"""
from __future__ import annotations

import logging
import statistics
import time
from pathlib import Path
from typing import Callable

import numpy as np
from PIL import Image

from omniscs.bench.harness import finish, load_line, machine_info, write_report
from omniscs.world.assets import list_asset_ids
from omniscs.world.render import WorldRenderer
from omniscs.world.traffic import generate_world

log = logging.getLogger(__name__)

#: The speed goal: a 40-frame, 3-camera 480x270 log with LiDAR in under this many seconds (2 CPU cores).
GOAL_SECONDS = 60.0
CASTER_REPEATS = 3


def compare_ray_casters(renderer: WorldRenderer, frame_idx: int = 0) -> dict:
    """Median seconds to cast one camera's rays against the static geometry: open3d vs embreex."""
    import open3d as o3d

    cam = renderer.world.cameras[0]
    d_cam, _ = renderer._camera_rays(cam)
    world_from_camera = renderer.world.ego_poses[frame_idx] @ cam.ego_from_camera
    d = (d_cam @ world_from_camera[:3, :3].T.astype(np.float32)).astype(np.float32)
    o = np.broadcast_to(world_from_camera[:3, 3].astype(np.float32), d.shape).copy()
    rays = o3d.core.Tensor(np.concatenate([o, d], 1))
    out = {"rays": int(len(d)), "triangles": int(len(renderer.layout.surface.faces))}
    times = []
    for _ in range(CASTER_REPEATS):
        t0 = time.perf_counter()
        renderer.static_scene.cast_rays(rays)["t_hit"].numpy()
        times.append(time.perf_counter() - t0)
    out["open3d_s"] = statistics.median(times)
    try:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh
    except ImportError:
        out["embreex_s"] = None
        return out
    surf = renderer.layout.surface
    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, surf.vertices.astype(np.float32)[surf.faces])
    times = []
    for _ in range(CASTER_REPEATS):
        t0 = time.perf_counter()
        scene.run(o, d, output=1)
        times.append(time.perf_counter() - t0)
    out["embreex_s"] = statistics.median(times)
    out["embreex_over_open3d"] = out["embreex_s"] / max(out["open3d_s"], 1e-9)
    return out


def run_world_benchmark(out_dir: Path, seeds=(0,), n_frames: int = 40, n_cameras: int = 3,
                        templates=("straight",), width: int = 480, height: int = 270, lighting: str = "day",
                        progress: Callable[[int, int], None] | None = None) -> dict:
    """Time generating and rendering (all cameras + LiDAR) one log per (template, seed); write JSON + Markdown."""
    machine = machine_info()
    runs = []
    total_steps = len(seeds) * len(templates) * n_frames
    done = 0
    for template in templates:
        for seed in seeds:
            t0 = time.perf_counter()
            world = generate_world(template, seed, n_frames=n_frames, n_cameras=n_cameras, width=width,
                                   height=height, lighting=lighting)
            t_generate = time.perf_counter() - t0
            t0 = time.perf_counter()
            renderer = WorldRenderer(world)
            t_setup = time.perf_counter() - t0
            camera_s, lidar_s, lidar_points = [], [], []
            for f in range(n_frames):
                t0 = time.perf_counter()
                images = [renderer.render_camera(f, cam.name).rgb for cam in world.cameras]
                camera_s.append(time.perf_counter() - t0)
                if f == 0 and not runs:
                    preview = np.concatenate(images, axis=1)
                t0 = time.perf_counter()
                lidar_points.append(len(renderer.lidar_scan(f)))
                lidar_s.append(time.perf_counter() - t0)
                done += 1
                if progress:
                    progress(done, total_steps)
            total = t_generate + t_setup + sum(camera_s) + sum(lidar_s)
            runs.append({
                "template": template, "seed": int(seed), "agents": len(world.agents),
                "static_triangles": int(len(renderer.layout.surface.faces)),
                "generate_s": t_generate, "renderer_setup_s": t_setup,
                "cameras_per_frame_median_s": statistics.median(camera_s),
                "lidar_per_frame_median_s": statistics.median(lidar_s),
                "lidar_points_median": int(statistics.median(lidar_points)),
                "total_s": total,
                "cameras_per_frame_s": camera_s, "lidar_per_frame_s": lidar_s,
            })
            log.info("%s seed %d: %.1f s for %d frames", template, seed, total, n_frames)
    casters = compare_ray_casters(renderer)
    result = {
        "benchmark": "world_render",
        "n_frames": n_frames, "n_cameras": n_cameras, "width": width, "height": height, "lighting": lighting,
        "ray_caster": "open3d.t.geometry.RaycastingScene",
        "ray_caster_comparison": casters,
        "asset_count": len(list_asset_ids()),
        "machine": finish(machine),
        "runs": runs,
        "median_total_s": statistics.median(r["total_s"] for r in runs),
        "goal_s": GOAL_SECONDS,
    }
    result["meets_goal"] = result["median_total_s"] < GOAL_SECONDS
    write_report(out_dir, "world", result, _markdown(result),
                 {"": lambda buf: _plot(result, buf),
                  "preview": lambda buf: Image.fromarray(preview).save(buf, format="PNG")})
    return result


def _plot(result: dict, buf) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.5))
    for run in result["runs"]:
        label = f"{run['template']} s{run['seed']}"
        ax.plot(run["cameras_per_frame_s"], label=f"{label}: {result['n_cameras']} cameras")
        ax.plot(run["lidar_per_frame_s"], linestyle="--", label=f"{label}: LiDAR")
    ax.set_xlabel("frame")
    ax.set_ylabel("seconds")
    ax.set_title(f"World render time per frame ({result['width']}x{result['height']})")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)


def _markdown(r: dict) -> str:
    lines = [
        "# Procedural world: generate + render",
        "",
        f"{r['n_frames']} frames x {r['n_cameras']} cameras at {r['width']}x{r['height']} + LiDAR, lighting "
        f"`{r['lighting']}`, ray caster `{r['ray_caster']}`, {r['asset_count']} assets in the library.",
        "",
        load_line(r["machine"]),
        "",
        "| template | seed | agents | generate s | cameras/frame s (median) | LiDAR/frame s (median) | total s |",
        "|---|---|---|---|---|---|---|",
    ]
    for run in r["runs"]:
        lines.append(f"| {run['template']} | {run['seed']} | {run['agents']} | {run['generate_s']:.2f} | "
                     f"{run['cameras_per_frame_median_s']:.3f} | {run['lidar_per_frame_median_s']:.3f} | "
                     f"{run['total_s']:.1f} |")
    c = r["ray_caster_comparison"]
    lines += ["", f"Median total: **{r['median_total_s']:.1f} s** (goal < {r['goal_s']:.0f} s: "
              f"{'met' if r['meets_goal'] else 'missed'}).", ""]
    if c.get("embreex_s") is not None:
        lines.append(f"Ray casters on {c['rays']} camera rays, {c['triangles']} static triangles: open3d "
                     f"{c['open3d_s'] * 1e3:.1f} ms, embreex {c['embreex_s'] * 1e3:.1f} ms "
                     f"(embreex/open3d = {c['embreex_over_open3d']:.2f}).")
    return "\n".join(lines) + "\n"
