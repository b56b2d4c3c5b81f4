"""Behaviour variants on CUDA (run by infra/gpu_check/run.sh on a GPU machine): the CUDA test of
tests/scs/test_behavior_adversarial.py on its straight road (a car in the next lane steered into the ego, the same
adversary as on the CPU), then three fast-preset variants of one procedural scene on each device: seconds and
outcomes. The traffic comes pickled (``GPU_CHECK_SCENES``/traffic.pkl, written by run.sh)."""
from __future__ import annotations

import os
import pickle
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from omniscs.scs.behavior.adversarial_config import adversarial_preset
from omniscs.scs.behavior.checkpoint import load_traffic_model
from omniscs.scs.behavior.generation import generate_variants

FAST = adversarial_preset("fast")
traffic = pickle.loads((Path(os.environ.get("GPU_CHECK_SCENES", ".gpu_check")) / "traffic.pkl").read_bytes())
model = load_traffic_model()
(v,) = generate_variants(traffic["straight"], model, 1, replace(FAST, device="cuda"))
(cpu,) = generate_variants(traffic["straight"], model, 1, FAST)
print("straight road, CUDA vs CPU:", {"success": v.success, "plausible": v.plausible,
                                      "same_adversary": v.adversary == cpu.adversary, "same_kind": v.kind == cpu.kind,
                                      "finite_losses": all(np.isfinite(x) for x in v.losses.values() if x is not None),
                                      "model_left_on_cpu": next(model.parameters()).device.type == "cpu"}, flush=True)
for device in ("cuda", "cpu"):
    started = time.perf_counter()
    out = generate_variants(traffic["t_junction"], model, 3, replace(FAST, device=device))
    print(f"3 fast variants of a t_junction scene on {device}: {time.perf_counter() - started:.1f} s, "
          f"successes {[x.success for x in out]}, adversaries {[x.adversary for x in out]} "
          f"(torch threads {torch.get_num_threads()})", flush=True)
