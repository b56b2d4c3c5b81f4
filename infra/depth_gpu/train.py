"""Train the embedded relative-depth network on a CUDA machine from exported training arrays.

The lent GPU machines lack the procedural world's packages (open3d), so `omniscs pretrained train reldepth
--device cuda` cannot run there whole. Its three parts run apart instead, with the same code:
  1. here:  omniscs pretrained train reldepth --export-data infra/depth_gpu/data/pack.zip
  2. there: python3 infra/depth_gpu/train.py infra/depth_gpu/data/pack.zip OUT --steps N [--workers 14]
  3. here:  omniscs pretrained train reldepth --install OUT   (held-out evaluation, training.json, shipped weights)
Step 2 needs only torch, numpy, OpenCV and safetensors. The configuration is DepthTrainConfig's defaults with the
overrides given here (all recorded in OUT/history.json).
"""
import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import torch  # noqa: E402

from omniscs.background.depth_pack import read_pack  # noqa: E402
from omniscs.background.depthnet import (DepthNetConfig, DepthTrainConfig, save_depth_net,  # noqa: E402
                                         train_depth_net)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("pack")
    ap.add_argument("out")
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--budget-s", type=float, default=None,
                    help="instead of --steps: as many steps (a multiple of 500) as fit this many seconds, measured "
                         "by a throw-away run of 200 steps first (the chosen count is printed and recorded)")
    ap.add_argument("--batch", type=int, default=None)
    ap.add_argument("--lr", type=float, default=None)
    ap.add_argument("--widths", default=None, help="comma-separated channels per level")
    ap.add_argument("--workers", type=int, default=14)
    ap.add_argument("--device", default="cuda")
    args = ap.parse_args()
    images, inv, repair = read_pack(args.pack)
    print(f"{len(images)} images ({int(repair.sum())} repair pairs) {images.shape[1:3]}", flush=True)
    cfg = DepthTrainConfig()
    over = {"steps": args.steps or 200, "workers": args.workers}
    if args.batch:
        over["batch"] = args.batch
    if args.lr:
        over["lr"] = args.lr
    if args.widths:
        over["architecture"] = DepthNetConfig(tuple(int(w) for w in args.widths.split(",")), cfg.architecture.long_side)
    cfg = dataclasses.replace(cfg, **over)
    calibration = None
    if args.steps is None:
        if args.budget_s is None:
            raise SystemExit("give --steps or --budget-s")
        t = {}

        def clock(i, n, msg):
            if i in (50, n):
                t[i] = time.perf_counter()

        train_depth_net(images, inv, cfg, clock, device=args.device)
        per_step = (t[cfg.steps] - t[50]) / (cfg.steps - 50)
        steps = max(500, int(args.budget_s / per_step) // 500 * 500)
        calibration = {"seconds_per_step": per_step, "budget_s": args.budget_s, "steps": steps}
        print(f"calibration: {per_step * 1000:.1f} ms per step -> {steps} steps", flush=True)
        cfg = dataclasses.replace(cfg, steps=steps)
    t0 = time.perf_counter()

    def progress(i, n, msg):
        if i % 250 == 0 or i == n:
            print(f"step {i}/{n} {msg} {time.perf_counter() - t0:.0f}s", flush=True)

    state, history = train_depth_net(images, inv, cfg, progress, device=args.device)
    history["device_name"] = torch.cuda.get_device_name() if args.device.startswith("cuda") else "cpu"
    history["torch"] = torch.__version__
    history["calibration"] = calibration
    save_depth_net(state, cfg.architecture, Path(args.out), history)
    print("loss", history["loss_first"], "->", history["loss_last"], "in", round(history["seconds"]), "s")


if __name__ == "__main__":
    main()
