"""Rasteriser benchmark: forward and forward+backward time per resolution, Gaussian count and backend.

Scene-like layout (``scenes.street_scene``): a road plane, two facades and car-sized boxes, scales
0.05-0.5 m, one camera at driving height looking down the street. Machines are shared and noisy:
compare backends as ratios within one run and read the load averages recorded with the results.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numba
import numpy as np
import torch

from omniscs.render.api import rasterize
from omniscs.bench.baseline import CURRENT_PACKAGE, run_probe
from omniscs.bench.harness import finish, machine_info, report_folder, write_report
from omniscs.storage import atomic_write_with
from omniscs.render.scenes import StreetScene, street_scene

log = logging.getLogger(__name__)

DEFAULT_RESOLUTIONS = ((320, 180), (640, 360), (1280, 720))
DEFAULT_COUNTS = (10_000, 100_000, 1_000_000)

#: The targets, for one 640x360 camera and 100k Gaussians on this 2-core machine (issue 55: twice the rates the
#: first rasteriser reached, 14.2 Hz and 5.1 Hz; the speed-up over the float64 reference from the first issue).
TARGET_RESOLUTION, TARGET_COUNT = (640, 360), 100_000
TARGET_FORWARD_HZ, TARGET_FORWARD_BACKWARD_HZ, TARGET_SPEEDUP = 30.0, 10.0, 20.0

#: The run that calibrates the reference's cost per pixel-Gaussian pair (to skip combos over budget)
#: and gives a speed-up measured on both backends even when every grid combo is too big for the reference.
CALIBRATION_RESOLUTION, CALIBRATION_COUNT = (160, 90), 3_000

#: Pixel-Gaussian pairs the reference may hold for one fwd+bwd (its checkpoints keep per-chunk state).
REFERENCE_MAX_PAIRS = 2e10


def _median_times(fn: Callable[[], Any], repeats: int) -> tuple[float, float]:
    """Median wall-clock and median process CPU seconds of ``repeats`` calls.

    CPU time counts every thread: CPU / wall is the number of cores the run actually had.
    """
    walls, cpus = [], []
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        fn()
        cpus.append(time.process_time() - cpu)
        walls.append(time.perf_counter() - wall)
    return statistics.median(walls), statistics.median(cpus)


def _measure(scene: StreetScene, backend: str, repeats: int) -> dict[str, float]:
    forward_s, forward_cpu_s = _median_times(_forward(scene, backend), repeats)
    forward_backward_s, forward_backward_cpu_s = _median_times(_forward_backward(scene, backend), repeats)
    return {"forward_s": forward_s, "forward_backward_s": forward_backward_s, "forward_hz": 1.0 / forward_s,
            "forward_backward_hz": 1.0 / forward_backward_s, "forward_cpu_s": forward_cpu_s,
            "forward_backward_cpu_s": forward_backward_cpu_s}


def _forward(scene: StreetScene, backend: str) -> Callable[[], Any]:
    def run() -> None:
        with torch.no_grad():
            rasterize(**scene.as_kwargs(), backend=backend)
    return run


def _forward_backward(scene: StreetScene, backend: str) -> Callable[[], Any]:
    names = ("means", "quats", "scales", "opacities", "colors")

    def run() -> None:
        params = {name: getattr(scene, name).detach().clone().requires_grad_(True) for name in names}
        colors, alphas, meta = rasterize(**{**scene.as_kwargs(), **params}, backend=backend)
        meta["means2d"].retain_grad()
        (colors.sum() + alphas.sum()).backward()
    return run


#: Run in a fresh interpreter so that memory freed by earlier steps cannot hide the peak. Prints JSON.
_MEMORY_PROBE = """
import json, sys, torch
from pathlib import Path
from omniscs.bench.harness import status_bytes
from omniscs.bench.render import _forward_backward
from omniscs.render.scenes import street_scene
width, height, count = map(int, sys.argv[1:4])
_forward_backward(street_scene(1_000, 64, 36), "cpu")()  # load the compiled kernels
scene = street_scene(count, width, height)
baseline = status_bytes("VmRSS")
_forward_backward(scene, "cpu")()
print(json.dumps({"baseline_rss_bytes": baseline, "peak_rss_bytes": status_bytes("VmHWM")}))
"""


def _measure_peak_memory(width: int, height: int, count: int) -> dict[str, Any]:
    """Peak resident memory added by one cpu forward+backward, measured in a fresh Python process."""
    probe = subprocess.run([sys.executable, "-c", _MEMORY_PROBE, str(width), str(height), str(count)],
                           capture_output=True, text=True, check=True)
    result = json.loads(probe.stdout.strip().splitlines()[-1])
    result["peak_increase_bytes"] = max(0, result["peak_rss_bytes"] - result["baseline_rss_bytes"])
    result["method"] = ("peak resident set (VmHWM) of a fresh process minus its resident set (VmRSS) after "
                        "building the scene, over one cpu forward+backward; includes the scene's tensors' "
                        "autograd state, bins and gradients, not the scene itself")
    return result


#: One side of a baseline comparison, in a fresh interpreter: the cpu backend's median forward and forward+backward
#: (wall and CPU) on the street scene. Only API that every revision has (rasterize, street_scene). Prints JSON.
_TIMING_PROBE = """
import json, statistics, sys, time
import torch
from omniscs.render import rasterize
from omniscs.render.scenes import street_scene
width, height, count, repeats = map(int, sys.argv[1:5])
names = ("means", "quats", "scales", "opacities", "colors")
def forward(scene):
    with torch.no_grad():
        rasterize(**scene.as_kwargs(), backend="cpu")
def forward_backward(scene):
    params = {n: getattr(scene, n).detach().clone().requires_grad_(True) for n in names}
    colors, alphas, meta = rasterize(**{**scene.as_kwargs(), **params}, backend="cpu")
    (colors.sum() + alphas.sum()).backward()
forward_backward(street_scene(1_000, 64, 36))
scene = street_scene(count, width, height)
forward(scene), forward_backward(scene)
out = {}
for name, run in (("forward", forward), ("forward_backward", forward_backward)):
    wall, cpu = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        run(scene)
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    out[name + "_s"], out[name + "_cpu_s"] = statistics.median(wall), statistics.median(cpu)
print(json.dumps(out))
"""


def compare_with_baseline(baseline: tuple[str, str, Path], resolutions, counts, repeats: int,
                          rounds: int) -> dict[str, Any]:
    """The cpu backend of ``baseline`` (ref, commit, folder holding its package) against the current code, per
    (resolution, count): ``rounds`` turns of each, alternating which goes first, each turn in a fresh process
    timing ``repeats`` runs; medians over the turns, and baseline / current as the speed-up."""
    ref, commit, tree = baseline
    sides = {"baseline": tree, "current": CURRENT_PACKAGE.parent}
    cells = []
    for width, height in resolutions:
        for count in counts:
            turns: dict[str, list[dict]] = {"baseline": [], "current": []}
            for k in range(rounds):
                for side in (("baseline", "current") if k % 2 == 0 else ("current", "baseline")):
                    turns[side].append(run_probe(sides[side], _TIMING_PROBE,
                                                 [str(width), str(height), str(count), str(repeats)]))
            cell = {"width": width, "height": height, "count": count}
            for side, got in turns.items():
                for key in ("forward_s", "forward_backward_s", "forward_cpu_s", "forward_backward_cpu_s"):
                    cell[f"{side}_{key}"] = statistics.median(t[key] for t in got)
            for key in ("forward_s", "forward_backward_s", "forward_cpu_s", "forward_backward_cpu_s"):
                cell[f"speedup_{key}"] = cell[f"baseline_{key}"] / cell[f"current_{key}"]
            cells.append(cell)
            log.info("%dx%d N=%d: forward %.2fx, forward+backward %.2fx faster than %s", width, height, count,
                     cell["speedup_forward_s"], cell["speedup_forward_backward_s"], ref)
    return {"ref": ref, "commit": commit, "rounds": rounds, "repeats": repeats, "cells": cells}


def run_render_benchmark(
    out_dir: Path,
    resolutions: tuple[tuple[int, int], ...] = DEFAULT_RESOLUTIONS,
    counts: tuple[int, ...] = DEFAULT_COUNTS,
    backends: tuple[str, ...] = ("cpu", "reference"),
    repeats: int = 5,
    reference_budget_s: float = 60.0,
    calibration_size: tuple[tuple[int, int], int] = (CALIBRATION_RESOLUTION, CALIBRATION_COUNT),
    baseline: tuple[str, str, Path] | None = None,
    baseline_rounds: int = 3,
) -> dict[str, Any]:
    """Time every (resolution, count, backend); write render/report.{json,md,png} and a sample render
    (render/sample.png) under the reports root ``out_dir``.

    Times are medians of ``repeats`` runs after one warm-up run (the reference runs once: it is the
    slow oracle). The reference is skipped, and recorded as skipped, where its predicted time
    exceeds ``reference_budget_s``. Compile (or cache-load) time of the Numba kernels is measured
    separately, on the first call. With ``baseline`` (ref, commit, folder holding that revision's package), the
    cpu backend of both is timed in turns per cell (``compare_with_baseline``) and the report gives the ratios.
    """
    machine = machine_info()
    start = time.perf_counter()
    _forward_backward(street_scene(1_000, 64, 36), "cpu")()
    first_call_s = time.perf_counter() - start

    calibration, reference_cost = None, None
    if "reference" in backends:
        (calib_width, calib_height), calib_count = calibration_size
        scene = street_scene(calib_count, calib_width, calib_height)
        _forward_backward(street_scene(200, 32, 18), "reference")()  # warm-up
        pairs = _visible_count(scene) * calib_width * calib_height
        calibration = {"width": calib_width, "height": calib_height, "count": calib_count, "pairs": pairs,
                       "reference": _measure(scene, "reference", 1), "cpu": _measure(scene, "cpu", repeats)}
        reference_cost = {key: calibration["reference"][key] / max(pairs, 1)
                          for key in ("forward_s", "forward_backward_s")}

    rows: list[dict[str, Any]] = []
    memory: dict[str, Any] = {}
    for width, height in resolutions:
        for count in counts:
            scene = street_scene(count, width, height)
            visible = _visible_count(scene)
            for backend in backends:
                row = {"width": width, "height": height, "count": count, "visible": visible, "backend": backend}
                if backend == "reference":
                    pairs = visible * width * height
                    predicted = pairs * reference_cost["forward_backward_s"]
                    if predicted > reference_budget_s or pairs > REFERENCE_MAX_PAIRS:
                        row.update(skipped=True, reason=f"predicted {predicted:.0f} s > budget {reference_budget_s:.0f} s")
                        rows.append(row)
                        log.info("skip reference %dx%d N=%d (predicted %.0f s)", width, height, count, predicted)
                        continue
                else:
                    _forward(scene, backend)()  # warm-up
                row.update(skipped=False, **_measure(scene, backend, 1 if backend == "reference" else repeats))
                rows.append(row)
                log.info("%s %dx%d N=%d: forward %.1f ms, forward+backward %.1f ms", backend, width, height, count,
                         row["forward_s"] * 1e3, row["forward_backward_s"] * 1e3)
            if count == max(counts) and "cpu" in backends:
                memory[f"{width}x{height}"] = _measure_peak_memory(width, height, count)

    results = {
        "machine": {**finish(machine), "numba_threading_layer": _threading_layer(),
                    "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "(unset: OpenMP threads spin)")},
        "settings": {"repeats": repeats, "reference_repeats": 1, "reference_budget_s": reference_budget_s,
                     "dtype": "float32", "scene": "street_scene (road, facades, cars; scales 0.05-0.5 m)"},
        "first_call_s": first_call_s,
        "calibration": calibration,
        "reference_cost_per_pair": reference_cost,
        "rows": rows,
        "speedups": _speedups(rows, calibration),
        "peak_memory_at_max_count": memory,
        "targets": None,
        "baseline": (compare_with_baseline(baseline, resolutions, counts, repeats, baseline_rounds)
                     if baseline is not None else None),
    }
    results["targets"] = _targets(rows, results["speedups"])
    write_report(out_dir, "render", results, render_markdown(results), {"": lambda buf: _plot(results, buf)})
    save_sample_render(report_folder(out_dir, "render") / "sample.png", *resolutions[0], max(counts))
    return results


def _threading_layer() -> str:
    try:
        return numba.threading_layer()
    except ValueError:  # no parallel function has run yet
        return "unknown"


def _visible_count(scene: StreetScene) -> int:
    with torch.no_grad():
        _, _, meta = rasterize(**scene.as_kwargs(), backend="cpu")
    return int((meta["radii"][..., 0] > 0).sum())


def _find(rows: list[dict[str, Any]], width: int, height: int, count: int, backend: str) -> dict[str, Any] | None:
    for row in rows:
        if (row["width"], row["height"], row["count"], row["backend"]) == (width, height, count, backend):
            return None if row["skipped"] else row
    return None


def _speedups(rows: list[dict[str, Any]], calibration: dict[str, Any] | None) -> list[dict[str, Any]]:
    """reference time / cpu time wherever both ran in this run (the calibration combo first)."""
    pairs = []
    if calibration is not None:
        pairs.append((calibration, calibration["cpu"], calibration["reference"], "calibration"))
    for row in rows:
        if row["backend"] == "cpu" and not row["skipped"]:
            ref = _find(rows, row["width"], row["height"], row["count"], "reference")
            if ref is not None:
                pairs.append((row, row, ref, "grid"))
    return [{"width": where["width"], "height": where["height"], "count": where["count"], "source": source,
             "forward": ref["forward_s"] / cpu["forward_s"],
             "forward_backward": ref["forward_backward_s"] / cpu["forward_backward_s"]}
            for where, cpu, ref, source in pairs]


def _targets(rows: list[dict[str, Any]], speedups: list[dict[str, Any]]) -> dict[str, Any]:
    cpu = _find(rows, *TARGET_RESOLUTION, TARGET_COUNT, "cpu")
    if cpu is None:
        return {"measured": False}
    smallest = min((s["forward_backward"] for s in speedups), default=None)
    return {
        "measured": True, "forward_hz": cpu["forward_hz"], "forward_backward_hz": cpu["forward_backward_hz"],
        "forward_met": cpu["forward_hz"] >= TARGET_FORWARD_HZ,
        "forward_backward_met": cpu["forward_backward_hz"] >= TARGET_FORWARD_BACKWARD_HZ,
        "cores_used_forward_backward": cpu["forward_backward_cpu_s"] / cpu["forward_backward_s"],
        "smallest_speedup": smallest, "speedup_met": None if smallest is None else smallest >= TARGET_SPEEDUP,
    }


def render_markdown(results: dict[str, Any]) -> str:
    """The results as a Markdown report (the table a person reads)."""
    machine = results["machine"]
    lines = [
        "# Rasteriser benchmark", "",
        f"Street scene, one camera, float32; medians of {results['settings']['repeats']} runs (reference: 1 run). "
        f"{machine['cpus']} CPUs, Numba {machine['numba_threads']} threads ({machine['numba_threading_layer']}), "
        f"load average before/after: {machine['load_average_start'][0]:.2f} / {machine['load_average_end'][0]:.2f}, "
        f"OMP_WAIT_POLICY {machine['OMP_WAIT_POLICY']}. "
        "Shared machine: compare within this run; CPU ms counts all threads, so CPU / wall is the number of "
        "cores the run really had.", "",
        f"First call (Numba compile or cache load): {results['first_call_s']:.1f} s.", "",
        "| resolution | Gaussians | visible | backend | forward ms | fwd+bwd ms | forward Hz | fwd+bwd Hz "
        "| forward CPU ms | fwd+bwd CPU ms |",
        "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|",
    ]
    for row in results["rows"]:
        head = f"| {row['width']}x{row['height']} | {row['count']:,} | {row['visible']:,} | {row['backend']} |"
        if row["skipped"]:
            lines.append(f"{head} skipped | {row['reason']} | | | | |")
        else:
            lines.append(f"{head} {row['forward_s'] * 1e3:.1f} | {row['forward_backward_s'] * 1e3:.1f} | "
                         f"{row['forward_hz']:.1f} | {row['forward_backward_hz']:.1f} | "
                         f"{row['forward_cpu_s'] * 1e3:.0f} | {row['forward_backward_cpu_s'] * 1e3:.0f} |")
    if results["speedups"]:
        lines += ["", "| measured on | resolution | Gaussians | cpu speed-up, forward | cpu speed-up, fwd+bwd |",
                  "|---|---|---:|---:|---:|"]
        for s in results["speedups"]:
            lines.append(f"| {s['source']} | {s['width']}x{s['height']} | {s['count']:,} | {s['forward']:.0f}x | "
                         f"{s['forward_backward']:.0f}x |")
    if results["peak_memory_at_max_count"]:
        lines += ["", "| resolution | peak RSS increase, cpu fwd+bwd at max count | method |", "|---|---:|---|"]
        for key, mem in results["peak_memory_at_max_count"].items():
            lines.append(f"| {key} | {mem['peak_increase_bytes'] / 2**20:.0f} MiB | {mem['method']} |")
    base = results.get("baseline")
    if base:
        lines += ["", f"Against {base['ref']} ({base['commit'][:12]}), the cpu backend of both timed in "
                  f"{base['rounds']} alternating turns of {base['repeats']} runs each, each turn in a fresh process; "
                  "medians over the turns. Speed-up = baseline time / current time (CPU: all threads' CPU time, "
                  "which the other processes on a shared machine disturb less than wall time).", "",
                  "| resolution | Gaussians | forward ms (baseline / now) | speed-up | fwd+bwd ms (baseline / now) "
                  "| speed-up | CPU speed-up fwd / fwd+bwd |", "|---|---:|---:|---:|---:|---:|---:|"]
        for c in base["cells"]:
            lines.append(f"| {c['width']}x{c['height']} | {c['count']:,} | {c['baseline_forward_s'] * 1e3:.1f} / "
                         f"{c['current_forward_s'] * 1e3:.1f} | {c['speedup_forward_s']:.2f}x | "
                         f"{c['baseline_forward_backward_s'] * 1e3:.1f} / {c['current_forward_backward_s'] * 1e3:.1f} "
                         f"| {c['speedup_forward_backward_s']:.2f}x | {c['speedup_forward_cpu_s']:.2f}x / "
                         f"{c['speedup_forward_backward_cpu_s']:.2f}x |")
    targets = results["targets"]
    if targets.get("measured"):
        lines += ["", f"Targets at {TARGET_RESOLUTION[0]}x{TARGET_RESOLUTION[1]}, {TARGET_COUNT:,} Gaussians: "
                  f"forward {targets['forward_hz']:.1f} Hz (target {TARGET_FORWARD_HZ:.0f}), "
                  f"forward+backward {targets['forward_backward_hz']:.1f} Hz (target {TARGET_FORWARD_BACKWARD_HZ:.0f}, "
                  f"with {targets['cores_used_forward_backward']:.1f} cores in use)"
                  + ("" if targets["smallest_speedup"] is None else
                     f", smallest measured speed-up {targets['smallest_speedup']:.0f}x (target {TARGET_SPEEDUP:.0f}x)") + "."]
    return "\n".join(lines) + "\n"


def _plot(results: dict[str, Any], buf) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    for ax, key, title in ((axes[0], "forward_s", "forward"), (axes[1], "forward_backward_s", "forward + backward")):
        series: dict[tuple[str, int, int], list[tuple[int, float]]] = {}
        for row in results["rows"]:
            if not row["skipped"]:
                series.setdefault((row["backend"], row["width"], row["height"]), []).append((row["count"], row[key] * 1e3))
        for (backend, width, height), points in sorted(series.items()):
            points.sort()
            ax.plot([p[0] for p in points], [p[1] for p in points], marker="o",
                    linestyle="-" if backend == "cpu" else "--", label=f"{backend} {width}x{height}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("Gaussians")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("time per frame (ms)")
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    try:
        fig.savefig(buf, format="png", dpi=110)
    finally:
        plt.close(fig)


#: Sky colour behind the sample render (RGB in [0, 1]) and the depth that maps to white in its depth panel.
SAMPLE_SKY = (0.62, 0.76, 0.95)
SAMPLE_DEPTH_RANGE_M = 80.0


def save_sample_render(path: Path, width: int = 640, height: int = 360, count: int = 100_000) -> Path:
    """Render the street scene with the cpu backend and save colour above expected depth as one PNG."""
    from PIL import Image

    scene = street_scene(count, width, height)
    with torch.no_grad():
        colors, _, _ = rasterize(**scene.as_kwargs(), render_mode="RGB+ED", backend="cpu",
                                 backgrounds=torch.tensor([SAMPLE_SKY]))
    rgb = (colors[0, ..., :3].clamp(0.0, 1.0).numpy() * 255).astype(np.uint8)
    depth = (np.clip(colors[0, ..., 3].numpy() / SAMPLE_DEPTH_RANGE_M, 0.0, 1.0) * 255).astype(np.uint8)
    panel = Image.fromarray(np.concatenate([rgb, np.repeat(depth[..., None], 3, -1)], 0))
    return atomic_write_with(path, lambda buf: panel.save(buf, format="PNG"))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--quick", action="store_true", help="small sizes only (a smoke run)")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.quick:
        results = run_render_benchmark(args.out_dir, resolutions=((160, 90),), counts=(1_000, 10_000), repeats=args.repeats)
    else:
        results = run_render_benchmark(args.out_dir, repeats=args.repeats)
    logging.getLogger(__name__).info("\n%s", render_markdown(results))


if __name__ == "__main__":
    main()
