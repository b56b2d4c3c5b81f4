"""A CUDA fit (run by infra/gpu_check/run.sh on a GPU machine): the checks of the CUDA test in
tests/nsg/test_nsg_device.py on a tiny scene, then one fast-preset fit of a small two-camera scene on CUDA (gsplat)
and on the CPU (the Numba rasterizer) with the same config: seconds and held-out PSNR of each."""
from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import torch

from omniscs.nsg import fit_preset, fit_scene, load_graph
from omniscs.plan import PlanConfig, make_plan
from omniscs.scene import load_scene

SCENES = Path(os.environ.get("GPU_CHECK_SCENES", ".gpu_check"))


def tiny_cuda_fit(out: Path) -> dict:
    scene = load_scene(SCENES / "scene_small")
    config = fit_preset("fast", iterations=20, resolution_schedule=((0.0, 1),), device="cuda",
                        plan=PlanConfig(gaussians_per_m2=0.5, gaussians_per_agent=400, min_gaussians=3_000,
                                        max_gaussians=8_000))
    result = fit_scene(scene, config, make_plan(scene, None, config.plan), checkpoint_dir=out)
    graph = result.graph
    rendered = graph.render(graph.view("CAM_FRONT", 2))
    on_cpu = load_graph(out, device="cpu")
    return {"graph_on_cuda": graph.device.type == "cuda" and all(a.gaussians.device.type == "cuda"
                                                                 for a in graph.agents),
            "sky_and_exposure_on_cuda": bool(graph.sky.texture.is_cuda
                                             and all(t.is_cuda for t in graph.exposure.values())),
            "render_on_cuda": bool(rendered.rgb.is_cuda), "backend": rendered.meta["backend"],
            "finite": bool(torch.isfinite(rendered.rgb).all() and torch.isfinite(rendered.depth).all()),
            "heldout_psnr": result.metrics["heldout_psnr"],
            "reloaded_on_cpu_renders_with": on_cpu.render(on_cpu.view("CAM_FRONT", 2)).meta["backend"]}


def main(iterations: int) -> None:
    print("tiny CUDA fit:", json.dumps(tiny_cuda_fit(Path("/tmp/gpu-check-tiny"))), flush=True)
    scene = load_scene(SCENES / "scene_big")
    for device in ("cuda", "cpu"):
        config = fit_preset("fast", iterations=iterations, device=device)
        started = time.perf_counter()
        result = fit_scene(scene, config, make_plan(scene, None, config.plan),
                           checkpoint_dir=Path(f"/tmp/gpu-check-{device}"))
        print(f"fast preset, {iterations} iterations, {device}: {time.perf_counter() - started:.1f} s, held-out "
              f"PSNR {result.metrics['heldout_psnr']:.2f} dB, {result.metrics.get('n_gaussians')} Gaussians "
              f"(torch threads {torch.get_num_threads()})", flush=True)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 300)
