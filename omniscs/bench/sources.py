"""Benchmark of the dataset readers: ingest time per frame for each format, on a synthetic log written in it.

Writes ``reports/sources/report.json`` and ``report.md``. Each format is read ``repeats`` times; the first read
(cold: imports, nuScenes table load) is reported apart from the median of the warm ones.
"""
from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

from omniscs.export import export_scenes
from omniscs.scene.sources import DatasetSource, read_dataset_scene
from omniscs.scene.store import load_scene
from omniscs.bench.harness import finish, load_line, machine_info, write_report
from omniscs.scene.synthetic import SyntheticSource, write_synthetic_scene

#: Readers measured: (label, export format, export options, source options).
CASES = (
    ("nuscenes keyframes", "nuscenes", {"version": "v1.0-mini", "keyframe_every": 1}, {}),
    ("nuscenes sweeps", "nuscenes", {"version": "v1.0-mini", "keyframe_every": 5}, {"sweeps": True}),
    ("kitti", "kitti", {}, {}),
    ("waymo-v2", "waymo-v2", {}, {}),
)


def run_sources_benchmark(out_dir: Path, n_frames: int = 10, n_cameras: int = 6, width: int = 480, height: int = 270,
                          repeats: int = 3, seed: int = 1) -> dict:
    """Render one synthetic log, write it in every format, and time reading each back into a scene store."""
    machine = machine_info()
    repeats = max(2, repeats)  # one cold read and at least one warm one
    rows = []
    with tempfile.TemporaryDirectory(prefix="omniscs-bench-sources-") as tmp:
        base = Path(tmp)
        source = SyntheticSource("straight", seed, "day", n_frames, n_cameras, width, height)
        store = write_synthetic_scene(source, base / "synthetic")
        for label, fmt, export_options, source_options in CASES:
            root = base / label.replace(" ", "-")
            t0 = time.perf_counter()
            export_scenes([store], fmt, root, **export_options)
            export_s = time.perf_counter() - t0
            times = []
            for r in range(repeats):
                t0 = time.perf_counter()
                out = read_dataset_scene(DatasetSource(fmt, str(root), **source_options), base / f"{root.name}-{r}")
                times.append(time.perf_counter() - t0)
            scene = load_scene(out)
            frames = scene.n_frames
            rows.append({
                "reader": label, "frames": frames, "cameras": len(scene.camera_names),
                "image_size": [width, height], "lidar_points_per_frame": len(scene.lidar(0)) if scene.has_lidar else 0,
                "boxes": len(scene.boxes), "export_s_per_frame": export_s / n_frames,
                "ingest_cold_s_per_frame": times[0] / frames,
                "ingest_s_per_frame_median": statistics.median(times[1:]) / frames,
            })
    result = {"machine": finish(machine), "n_frames": n_frames, "n_cameras": n_cameras, "repeats": repeats,
              "results": rows}
    write_report(out_dir, "sources", result, _markdown(result))
    return result


def _markdown(result: dict) -> str:
    lines = [f"# Dataset ingest time per frame ({result['n_frames']}-frame synthetic log, "
             f"{result['n_cameras']} cameras written where the format has them)", "",
             "| reader | frames | cameras | image | LiDAR points/frame | ingest ms/frame (warm median) | "
             "ingest ms/frame (cold) | export ms/frame |", "|---|---|---|---|---|---|---|---|"]
    for r in result["results"]:
        lines.append(f"| {r['reader']} | {r['frames']} | {r['cameras']} | {r['image_size'][0]}x{r['image_size'][1]} | "
                     f"{r['lidar_points_per_frame']} | {1000 * r['ingest_s_per_frame_median']:.0f} | "
                     f"{1000 * r['ingest_cold_s_per_frame']:.0f} | {1000 * r['export_s_per_frame']:.0f} |")
    lines += ["", f"Medians of {result['repeats'] - 1} warm reads. {load_line(result['machine'])}"]
    return "\n".join(lines) + "\n"
