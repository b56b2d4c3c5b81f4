"""The embedded inpainting network's data and its shipped weights: repair pairs of procedural worlds (a camera image
with a large agent in it, the agent's hole, and the same view of the world without that agent: what lies behind
it, exactly), packs to train on another machine, the held-out evaluation against the classical inpainters, and
installing the weights.

Seeds: training worlds 3000-3255 (the default; the shipped pack was cut to fewer, see training.json), held-out
worlds 3900-3919; never below 3000 (the benchmarks' worlds).
"""
from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
from safetensors.torch import load_file

from omniscs.background.depthnet import working_size
from omniscs.background.inpaint import OpenCVInpainter
from omniscs.background.inpaint_pack import write_pack
from omniscs.background.inpaintnet import (
    INFO_FILE,
    SHIPPED,
    WEIGHTS_FILE,
    InpaintNet,
    InpaintNetConfig,
    NetInpainter,
    save_inpaint_net,
)
from omniscs.training.reldepth import FIRST_DEPTH_SEED, rendered_views
from omniscs.bench.harness import finish, machine_info
from omniscs.errors import OmniscsError
from omniscs.progress import Progress, no_progress
from omniscs.quality import UINT8_RANGE, psnr, psnr_from_mse
from omniscs.storage import atomic_write_with, content_hash, workspace_root
from omniscs.untrusted import read_own_json

log = logging.getLogger(__name__)

#: Bump when the way samples are made changes, so that cached data are made again.
DATA_VERSION = 1

TRAIN_COMMAND = "omniscs pretrained train inpaint --export-data PACK (then infra/inpaint_gpu/train.py, " \
                "omniscs pretrained train inpaint --install OUT)"


@dataclass(frozen=True)
class InpaintDataConfig:
    """Which procedural views make the repair pairs that train and evaluate the embedded inpainting network."""

    train_seeds: tuple[int, ...] = tuple(range(3000, 3256))
    """Training worlds (template and lighting follow from the seed, as for the depth data)."""
    eval_seeds: tuple[int, ...] = tuple(range(3900, 3920))
    """Held-out worlds of the evaluation in training.json."""
    templates: tuple[str, ...] = ("straight", "t_junction", "intersection", "straight_parked_truck")
    """World templates, taken in turn by seed."""
    lightings: tuple[str, ...] = ("day", "dusk", "night", "fog")
    """Lightings, taken in turn by blocks of ``len(templates)`` seeds."""
    frames: tuple[int, ...] = (4, 14, 24, 34)
    """Frames rendered of each world's log (all cameras of each)."""
    n_frames: int = 40
    """Frames of each generated log."""
    n_cameras: int = 6
    """Cameras of the rig rendered."""
    width: int = 320
    """Rendered image width (pixels)."""
    height: int = 180
    """Rendered image height (pixels)."""
    long_side: int = 256
    """Long side of the training images (256 x 144: near the repair's working resolution, 240 x 135 for the
    benchmarks' 480 x 270 logs at factor 2)."""
    removal_min_fraction: float = 0.02
    """A view gives a pair when its largest agent covers at least this fraction of the image."""
    max_hole_fraction: float = 0.7
    """Views whose hole covers more of the image are left out (the repair inpaints only views with 20 % known
    pixels or more; a view filled by an agent teaches nothing about filling from context)."""
    hole_dilation_px: int = 2
    """The hole, the convex hull of the agent's pixels (as the repair's holes are box projections, not
    silhouettes), is grown by this many pixels at the working resolution."""


def repair_pairs(seed: int, config: InpaintDataConfig) -> dict[str, np.ndarray]:
    """The pairs of the world of ``seed`` at the working resolution: ``images`` uint8 [N, h, w, 3] (with the
    agent), ``holes`` bool [N, h, w], ``targets`` uint8 [N, h, w, 3] (the world without the agent)."""
    h, w = working_size(config.height, config.width, config.long_side)
    images, holes, targets = [], [], []
    for view in rendered_views(seed, config):
        if "agent" not in view:
            continue
        agent = cv2.resize(view["agent"].astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST)
        points = cv2.findNonZero(agent)
        if points is None:
            continue
        hole = np.zeros((h, w), np.uint8)
        cv2.fillConvexPoly(hole, cv2.convexHull(points), 1)
        k = 2 * config.hole_dilation_px + 1
        hole = cv2.dilate(hole, np.ones((k, k), np.uint8)).astype(bool)
        if hole.mean() > config.max_hole_fraction:
            continue
        images.append(cv2.resize(view["rgb"], (w, h), interpolation=cv2.INTER_AREA))
        targets.append(cv2.resize(view["removed_rgb"], (w, h), interpolation=cv2.INTER_AREA))
        holes.append(hole)
    if not images:
        return {"images": np.zeros((0, h, w, 3), np.uint8), "holes": np.zeros((0, h, w), bool),
                "targets": np.zeros((0, h, w, 3), np.uint8)}
    return {"images": np.stack(images), "holes": np.stack(holes), "targets": np.stack(targets)}


def _cache_dir(config: InpaintDataConfig, workspace: Path) -> Path:
    key = content_hash(DATA_VERSION, asdict(config) | {"train_seeds": None, "eval_seeds": None})[:12]
    return workspace / "bench-background" / f"inpaint-data-{key}"


def cached_pairs(seeds, config: InpaintDataConfig, workspace: Path | None = None,
                 progress: Progress = no_progress) -> dict[str, np.ndarray]:
    """``repair_pairs`` of every seed, concatenated; each world's pairs are cached under the workspace (so an
    interrupted run resumes, and several processes can fill the cache for disjoint seeds)."""
    if any(int(s) < FIRST_DEPTH_SEED for s in seeds):
        raise OmniscsError(f"inpainting data use seeds >= {FIRST_DEPTH_SEED} (the benchmarks use the lower ones)")
    folder = _cache_dir(config, workspace_root(workspace))
    parts = []
    for i, seed in enumerate(seeds):
        progress(i, len(seeds), f"inpainting data: world {seed}")
        path = folder / f"{int(seed)}.npz"
        if path.is_file():
            with np.load(path) as z:
                parts.append({k: z[k] for k in ("images", "holes", "targets")})
            continue
        pairs = repair_pairs(int(seed), config)
        atomic_write_with(path, lambda fh: np.savez_compressed(fh, **pairs))
        parts.append(pairs)
    progress(len(seeds), len(seeds), "inpainting data: done")
    return {k: np.concatenate([p[k] for p in parts]) for k in ("images", "holes", "targets")}


def _check_seeds(data: InpaintDataConfig) -> None:
    if any(s < FIRST_DEPTH_SEED for s in data.train_seeds + data.eval_seeds):
        raise OmniscsError(f"inpainting data use seeds >= {FIRST_DEPTH_SEED} (the benchmarks use the lower ones)")
    if set(data.train_seeds) & set(data.eval_seeds):
        raise OmniscsError("the held-out seeds of the inpainting evaluation must not be training seeds")


def export_inpaint_data(path: Path, workspace: Path | None = None, data: InpaintDataConfig = InpaintDataConfig(),
                        progress: Progress = no_progress) -> dict:
    """Render (or reuse) the training pairs and write them as a pack to ``path``, to train the network on a
    machine without the procedural world. Returns the pack's facts."""
    _check_seeds(data)
    pairs = cached_pairs(data.train_seeds, data, workspace, progress)
    size = write_pack(path, pairs["images"], pairs["holes"], pairs["targets"])
    return {"path": str(path), "bytes": size, "n_pairs": int(len(pairs["images"])),
            "hole_share_mean": float(pairs["holes"].mean()), "data": asdict(data)}


# ----------------------------------------------------------------------------- evaluation
def hole_psnr(filled: np.ndarray, target: np.ndarray, hole: np.ndarray) -> float | None:
    """PSNR (dB, 8-bit scale) of ``filled`` against ``target`` over the ``hole`` pixels (``omniscs.quality``)."""
    return psnr(filled, target, hole, data_range=UINT8_RANGE)


def evaluate_inpainters(inpainters: dict, pairs: dict[str, np.ndarray]) -> dict:
    """Per inpainter (name -> Inpainter): hole PSNR and mean absolute error (grey levels) over the pairs, the
    mean of per-pair values and the pooled PSNR of all hole pixels, and seconds per image."""
    report = {}
    for name, inpainter in inpainters.items():
        psnrs, abs_err, sq, n = [], [], 0.0, 0
        started = time.perf_counter()
        for image, hole, target in zip(pairs["images"], pairs["holes"], pairs["targets"]):
            filled = inpainter.inpaint(image, hole)
            psnrs.append(hole_psnr(filled, target, hole))
            diff = filled[hole].astype(np.float64) - target[hole].astype(np.float64)
            abs_err.append(float(np.abs(diff).mean()))
            sq += float((diff ** 2).sum())
            n += diff.size
        seconds = time.perf_counter() - started
        report[name] = {"n_pairs": len(psnrs), "hole_psnr_mean": float(np.mean(psnrs)),
                        "hole_psnr_median": float(np.median(psnrs)),
                        "hole_psnr_pooled": psnr_from_mse(sq / max(n, 1), UINT8_RANGE),
                        "hole_abs_error_mean": float(np.mean(abs_err)),
                        "seconds_per_image": seconds / max(1, len(psnrs))}
    return report


def shipping_info(state: dict, history: dict, data: InpaintDataConfig = InpaintDataConfig(),
                  workspace: Path | None = None) -> dict:
    """training.json's content for weights ``state``: the history and the held-out evaluation of the network
    against OpenCV's FSR (the repair's classical default) and Telea."""
    _check_seeds(data)
    started = time.perf_counter()
    net = InpaintNet(InpaintNetConfig.from_dict(history["config"]["architecture"]))
    net.load_state_dict(state)
    pairs = cached_pairs(data.eval_seeds, data, workspace)
    evaluation = evaluate_inpainters({"embedded": NetInpainter(net.eval()), "fsr_fast": OpenCVInpainter("fsr_fast"),
                                      "telea": OpenCVInpainter("telea")}, pairs)
    return {"command": TRAIN_COMMAND, "data": asdict(data), "data_version": DATA_VERSION, **history,
            "evaluation": {"held_out_seeds": list(data.eval_seeds), "n_pairs": int(len(pairs["images"])),
                           "hole_share_mean": float(pairs["holes"].mean()),
                           "protocol": "each held-out pair's hole filled from the image around it; PSNR and mean "
                                       "absolute error inside the hole against the world rendered without the agent",
                           **evaluation},
            "seconds_eval": time.perf_counter() - started}


def install_trained_inpaint(folder: Path, data: InpaintDataConfig = InpaintDataConfig(), out: Path | None = None,
                            workspace: Path | None = None) -> dict:
    """Evaluate the weights infra/inpaint_gpu/train.py saved into ``folder`` on the held-out worlds and write them
    with that evaluation to ``out`` (the shipped weights by default)."""
    folder = Path(folder)
    try:
        state = load_file(str(folder / WEIGHTS_FILE))
        history = read_own_json(folder / INFO_FILE, f"{folder} holds no weights from infra/inpaint_gpu/train.py",
                                expect=dict)
    except (OSError, ValueError) as e:
        raise OmniscsError(f"{folder} holds no weights from infra/inpaint_gpu/train.py ({type(e).__name__}: {e})") \
            from e
    history.pop("architecture", None)
    info = shipping_info(state, history, data, workspace)
    info["trained_elsewhere"] = (f"trained on {history.get('device_name', history.get('device'))} (torch "
                                 f"{history.get('torch')}) by infra/inpaint_gpu/train.py from the pack of "
                                 "`omniscs pretrained train inpaint --export-data`; evaluated and installed here with "
                                 "`omniscs pretrained train inpaint --install`")
    info["machine_eval"] = finish(machine_info())
    save_inpaint_net(state, InpaintNetConfig.from_dict(history["config"]["architecture"]), out or SHIPPED, info)
    return info
