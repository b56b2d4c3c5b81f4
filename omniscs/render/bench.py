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
import platform
import resource
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import numba
import torch

from omniscs.render.api import rasterize
from omniscs.render.scenes import StreetScene, street_scene

log = logging.getLogger(__name__)

DEFAULT_RESOLUTIONS = ((320, 180), (640, 360), (1280, 720))
DEFAULT_COUNTS = (10_000, 100_000, 1_000_000)

#: The issue's targets, for one 640x360 camera and 100k Gaussians on this 2-core machine.
TARGET_RESOLUTION, TARGET_COUNT = (640, 360), 100_000
TARGET_FORWARD_HZ, TARGET_FORWARD_BACKWARD_HZ, TARGET_SPEEDUP = 10.0, 3.0, 20.0

#: Size of the run that calibrates the reference's cost per pixel-Gaussian pair.
CALIBRATION_RESOLUTION, CALIBRATION_COUNT = (96, 54), 2_000

#: Backward costs this many forwards at most (used only to predict reference times for skipping).
BACKWARD_COST_FACTOR = 4.0

#: Pixel-Gaussian pairs the reference may hold for one fwd+bwd (its checkpoints keep per-chunk state).
REFERENCE_MAX_PAIRS = 2e10


def _median_time(fn: Callable[[], Any], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


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


def _reset_peak_rss() -> str:
    """Reset the kernel's peak-RSS counter if allowed; say which measure the next reading is."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return "VmHWM after resetting it via /proc/self/clear_refs (peak resident set of this step)"
    except OSError:
        return "ru_maxrss increase (process-lifetime peak; 0 when an earlier step peaked higher)"


def _peak_rss_bytes() -> int:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _current_rss_bytes() -> int:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def _measure_peak_memory(scene: StreetScene) -> dict[str, Any]:
    method = _reset_peak_rss()
    baseline = _current_rss_bytes() if method.startswith("VmHWM") else _peak_rss_bytes()
    _forward_backward(scene, "cpu")()
    peak = _peak_rss_bytes()
    return {"peak_rss_bytes": peak, "baseline_rss_bytes": baseline, "peak_increase_bytes": max(0, peak - baseline),
            "method": method}


def _write_atomic(path: Path, data: bytes) -> None:
    with tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{path.name}.", delete=False) as tmp:
        tmp.write(data)
    os.replace(tmp.name, path)


def run_render_benchmark(
    out_dir: Path,
    resolutions: tuple[tuple[int, int], ...] = DEFAULT_RESOLUTIONS,
    counts: tuple[int, ...] = DEFAULT_COUNTS,
    backends: tuple[str, ...] = ("cpu", "reference"),
    repeats: int = 5,
    reference_budget_s: float = 30.0,
) -> dict[str, Any]:
    """Time every (resolution, count, backend); write render_bench.{json,md,png} to out_dir; return the results.

    Times are medians of ``repeats`` runs after one warm-up run (the reference runs once: it is the
    slow oracle). The reference is skipped, and recorded as skipped, where its predicted time
    exceeds ``reference_budget_s``. Compile (or cache-load) time of the Numba kernels is measured
    separately, on the first call.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()
    start = time.perf_counter()
    _forward_backward(street_scene(1_000, 64, 36), "cpu")()
    first_call_s = time.perf_counter() - start

    reference_cost = None
    if "reference" in backends:
        calib = street_scene(CALIBRATION_COUNT, *CALIBRATION_RESOLUTION)
        pairs = _visible_count(calib) * CALIBRATION_RESOLUTION[0] * CALIBRATION_RESOLUTION[1]
        _forward(calib, "reference")()
        reference_cost = {
            "forward_s_per_pair": _median_time(_forward(calib, "reference"), 1) / max(pairs, 1),
            "forward_backward_s_per_pair": _median_time(_forward_backward(calib, "reference"), 1) / max(pairs, 1),
        }

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
                    predicted = pairs * reference_cost["forward_backward_s_per_pair"]
                    if predicted > reference_budget_s or pairs > REFERENCE_MAX_PAIRS:
                        row.update(skipped=True, reason=f"predicted {predicted:.0f} s > budget {reference_budget_s:.0f} s")
                        rows.append(row)
                        log.info("skip reference %dx%d N=%d (predicted %.0f s)", width, height, count, predicted)
                        continue
                    n_repeats = 1
                else:
                    n_repeats = repeats
                    _forward(scene, backend)()  # warm-up
                forward_s = _median_time(_forward(scene, backend), n_repeats)
                forward_backward_s = _median_time(_forward_backward(scene, backend), n_repeats)
                row.update(skipped=False, forward_s=forward_s, forward_backward_s=forward_backward_s,
                           forward_hz=1.0 / forward_s, forward_backward_hz=1.0 / forward_backward_s)
                rows.append(row)
                log.info("%s %dx%d N=%d: forward %.1f ms, forward+backward %.1f ms", backend, width, height, count,
                         forward_s * 1e3, forward_backward_s * 1e3)
            if count == max(counts) and "cpu" in backends:
                memory[f"{width}x{height}"] = _measure_peak_memory(scene)

    results = {
        "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(), "numba_threads": numba.get_num_threads(),
                    "torch_threads": torch.get_num_threads(), "numba_threading_layer": _threading_layer(),
                    "load_average_before": load_before, "load_average_after": os.getloadavg()},
        "settings": {"repeats": repeats, "reference_repeats": 1, "reference_budget_s": reference_budget_s,
                     "dtype": "float32", "scene": "street_scene (road, facades, cars; scales 0.05-0.5 m)"},
        "first_call_s": first_call_s,
        "reference_cost": reference_cost,
        "rows": rows,
        "speedups": _speedups(rows),
        "peak_memory_at_max_count": memory,
        "targets": _targets(rows),
    }
    _write_atomic(out_dir / "render_bench.json", json.dumps(results, indent=2).encode())
    _write_atomic(out_dir / "render_bench.md", render_markdown(results).encode())
    _plot(results, out_dir / "render_bench.png")
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


def _speedups(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """reference time / cpu time wherever both ran in this run."""
    out = []
    for row in rows:
        if row["backend"] != "cpu" or row["skipped"]:
            continue
        ref = _find(rows, row["width"], row["height"], row["count"], "reference")
        if ref is not None:
            out.append({"width": row["width"], "height": row["height"], "count": row["count"],
                        "forward": ref["forward_s"] / row["forward_s"],
                        "forward_backward": ref["forward_backward_s"] / row["forward_backward_s"]})
    return out


def _targets(rows: list[dict[str, Any]]) -> dict[str, Any]:
    cpu = _find(rows, *TARGET_RESOLUTION, TARGET_COUNT, "cpu")
    if cpu is None:
        return {"measured": False}
    speedups = _speedups(rows)
    best = min((s["forward_backward"] for s in speedups), default=None)
    return {
        "measured": True, "forward_hz": cpu["forward_hz"], "forward_backward_hz": cpu["forward_backward_hz"],
        "forward_met": cpu["forward_hz"] >= TARGET_FORWARD_HZ,
        "forward_backward_met": cpu["forward_backward_hz"] >= TARGET_FORWARD_BACKWARD_HZ,
        "smallest_speedup": best, "speedup_met": None if best is None else best >= TARGET_SPEEDUP,
    }


def render_markdown(results: dict[str, Any]) -> str:
    """The results as a Markdown report (the table a person reads)."""
    machine = results["machine"]
    lines = [
        "# Rasteriser benchmark", "",
        f"Street scene, one camera, float32; medians of {results['settings']['repeats']} runs (reference: 1 run). "
        f"{machine['cpu_count']} CPUs, Numba {machine['numba_threads']} threads ({machine['numba_threading_layer']}), "
        f"load average before/after: {machine['load_average_before'][0]:.2f} / {machine['load_average_after'][0]:.2f} "
        "(shared machine: compare within this run).", "",
        f"First call (Numba compile or cache load): {results['first_call_s']:.1f} s.", "",
        "| resolution | Gaussians | visible | backend | forward ms | fwd+bwd ms | forward Hz | fwd+bwd Hz |",
        "|---|---:|---:|---|---:|---:|---:|---:|",
    ]
    for row in results["rows"]:
        head = f"| {row['width']}x{row['height']} | {row['count']:,} | {row['visible']:,} | {row['backend']} |"
        if row["skipped"]:
            lines.append(f"{head} skipped | {row['reason']} | | |")
        else:
            lines.append(f"{head} {row['forward_s'] * 1e3:.1f} | {row['forward_backward_s'] * 1e3:.1f} | "
                         f"{row['forward_hz']:.1f} | {row['forward_backward_hz']:.1f} |")
    if results["speedups"]:
        lines += ["", "| resolution | Gaussians | cpu speed-up, forward | cpu speed-up, fwd+bwd |", "|---|---:|---:|---:|"]
        for s in results["speedups"]:
            lines.append(f"| {s['width']}x{s['height']} | {s['count']:,} | {s['forward']:.0f}x | {s['forward_backward']:.0f}x |")
    if results["peak_memory_at_max_count"]:
        lines += ["", "| resolution | peak RSS increase, cpu fwd+bwd at max count | method |", "|---|---:|---|"]
        for key, mem in results["peak_memory_at_max_count"].items():
            lines.append(f"| {key} | {mem['peak_increase_bytes'] / 2**20:.0f} MiB | {mem['method']} |")
    targets = results["targets"]
    if targets.get("measured"):
        lines += ["", f"Targets at {TARGET_RESOLUTION[0]}x{TARGET_RESOLUTION[1]}, {TARGET_COUNT:,} Gaussians: "
                  f"forward {targets['forward_hz']:.1f} Hz (target {TARGET_FORWARD_HZ:.0f}), "
                  f"forward+backward {targets['forward_backward_hz']:.1f} Hz (target {TARGET_FORWARD_BACKWARD_HZ:.0f})"
                  + ("" if targets["smallest_speedup"] is None else
                     f", smallest measured speed-up {targets['smallest_speedup']:.0f}x (target {TARGET_SPEEDUP:.0f}x)") + "."]
    return "\n".join(lines) + "\n"


def _plot(results: dict[str, Any], path: Path) -> None:
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
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)


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
