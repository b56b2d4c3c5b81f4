"""Train the embedded inpainting network on a CUDA machine from an exported pack of repair pairs.

The lent GPU machines lack the procedural world's packages, so the work runs in three parts with the same code:
  1. here:  omniscs pretrained train inpaint --export-data infra/inpaint_gpu/data/pack.zip
  2. there: python3 infra/inpaint_gpu/train.py infra/inpaint_gpu/data/pack.zip OUT --budget-s 300 [--workers 14]
  3. here:  omniscs pretrained train inpaint --install OUT   (held-out evaluation, training.json, shipped weights)
Step 2 needs only torch, numpy, OpenCV and safetensors. The configuration is InpaintTrainConfig's defaults with the
overrides given here (all recorded in OUT/training.json).
"""
import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import torch  # noqa: E402

from omniscs.background.inpaintnet import InpaintTrainConfig, save_inpaint_net, train_inpaint_net  # noqa: E402
from omniscs.background.inpaint_pack import read_pack  # noqa: E402


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
    ap.add_argument("--workers", type=int, default=14)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--init", default=None, help="a folder this script wrote: train on from its weights (a second "
                                                 "phase; its training.json is kept in the new one under 'first_phase')")
    args = ap.parse_args()
    pairs = read_pack(args.pack)
    images, holes, targets = pairs["images"], pairs["holes"], pairs["targets"]
    print(f"{len(images)} pairs {images.shape[1:3]}, hole share {holes.mean():.3f}", flush=True)
    over = {"steps": args.steps or 200, "workers": args.workers}
    if args.batch:
        over["batch"] = args.batch
    if args.lr:
        over["lr"] = args.lr
    cfg = dataclasses.replace(InpaintTrainConfig(), **over)
    init, first = None, None
    if args.init:
        import json

        from safetensors.torch import load_file

        from omniscs.background.inpaintnet import INFO_FILE, WEIGHTS_FILE
        init = load_file(str(Path(args.init) / WEIGHTS_FILE))
        first = json.loads((Path(args.init) / INFO_FILE).read_text())
    calibration = None
    if args.steps is None:
        if args.budget_s is None:
            raise SystemExit("give --steps or --budget-s")
        t = {}

        def clock(i, n, msg):
            if i in (50, n):
                t[i] = time.perf_counter()

        train_inpaint_net(images, holes, targets, cfg, clock, device=args.device, init=init)
        per_step = (t[cfg.steps] - t[50]) / (cfg.steps - 50)
        steps = max(500, int(args.budget_s / per_step) // 500 * 500)
        calibration = {"seconds_per_step": per_step, "budget_s": args.budget_s, "steps": steps}
        print(f"calibration: {per_step * 1000:.1f} ms per step -> {steps} steps", flush=True)
        cfg = dataclasses.replace(cfg, steps=steps)
    t0 = time.perf_counter()

    def progress(i, n, msg):
        if i % 500 == 0 or i == n:
            print(f"step {i}/{n} {msg} {time.perf_counter() - t0:.0f}s", flush=True)

    state, history = train_inpaint_net(images, holes, targets, cfg, progress, device=args.device, init=init)
    history["device_name"] = torch.cuda.get_device_name() if args.device.startswith("cuda") else "cpu"
    history["torch"] = torch.__version__
    history["calibration"] = calibration
    if first is not None:
        first.pop("architecture", None)
        history["first_phase"] = first
    save_inpaint_net(state, cfg.architecture, Path(args.out), history)
    print("loss", history["loss_first"], "->", history["loss_last"], "in", round(history["seconds"]), "s")


if __name__ == "__main__":
    main()
