"""Both rasterizer backends timed on one random scene per size (run by infra/gpu_check/run.sh on a GPU machine):
milliseconds per rendered frame, after one warm-up call."""
from __future__ import annotations

import time

import torch

from omniscs.render import rasterize
from omniscs.render.scenes import random_scene

KEYS = ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks")

for n, w, h in ((20_000, 640, 360), (200_000, 1600, 900)):
    s = random_scene(n, w, h, n_cameras=1, seed=3, dtype=torch.float32)
    for device, backend, reps in (("cuda", "gsplat", 20), ("cpu", "cpu", 3)):
        kwargs = {k: getattr(s, k).to(device) for k in KEYS}
        rasterize(**kwargs, width=w, height=h, backend=backend)
        torch.cuda.synchronize()
        started = time.perf_counter()
        for _ in range(reps):
            rasterize(**kwargs, width=w, height=h, backend=backend)
        torch.cuda.synchronize()
        print(f"{n} Gaussians, {w}x{h}, {backend}: {(time.perf_counter() - started) / reps * 1000:.1f} ms per frame "
              f"(torch threads {torch.get_num_threads()})")
