"""The embedded relative-depth network's data and its shipped weights: camera images of procedural worlds with their
exact depth, pairs that imitate background repair (a large agent's pixels inpainted, the target the depth of the
world without it), the held-out evaluation against that ground truth, and ``train_shipped_depth``.

Seeds: training worlds 3000-3127 (the default; more may be asked for), held-out worlds 3900-3909; never below 3000 (the
benchmarks' worlds).
"""
from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Iterator

import cv2
import numpy as np
from safetensors.torch import load_file
from scipy.stats import rankdata

from omniscs.background.depth import SHIPPED, TRAIN_COMMAND
from omniscs.background.depth_pack import write_pack
from omniscs.background.depthnet import (INFO_FILE, WEIGHTS_FILE, DepthNet, DepthTrainConfig, predict_inverse_depth,
                                         save_depth_net, scale_shift_align, train_depth_net, working_size)
from omniscs.bench.harness import finish, machine_info
from omniscs.errors import OmniscsError
from omniscs.progress import Progress, no_progress
from omniscs.storage import atomic_write_with, content_hash, workspace_root
from omniscs.untrusted import read_own_json
from omniscs.world import WorldRenderer, generate_world

log = logging.getLogger(__name__)

#: Bump when the way samples are made changes, so that cached data are made again.
DATA_VERSION = 1

#: Seeds the benchmarks use lie below this one; depth data never touches them.
FIRST_DEPTH_SEED = 3000

INPAINT_METHODS = ("fsr_fast", "telea", "ns")
"""Classical inpainters that fill the removed agent's pixels: OpenCV xphoto FSR (fast), Telea, Navier-Stokes."""


@dataclass(frozen=True)
class DepthDataConfig:
    """Which procedural camera images train and evaluate the embedded relative-depth network, and how the
    background-repair pairs among them are made."""

    train_seeds: tuple[int, ...] = tuple(range(3000, 3128))
    """Training worlds (one per seed; template and lighting follow from the seed)."""
    eval_seeds: tuple[int, ...] = tuple(range(3900, 3910))
    """Held-out worlds of the evaluation in training.json."""
    templates: tuple[str, ...] = ("straight", "t_junction", "intersection", "straight_parked_truck")
    """World templates, taken in turn by seed."""
    lightings: tuple[str, ...] = ("day", "dusk", "night", "fog")
    """Lightings, taken in turn by blocks of ``len(templates)`` seeds (so every template meets every lighting)."""
    frames: tuple[int, ...] = (8, 28)
    """Frames rendered of each world's log (all cameras of each)."""
    n_frames: int = 40
    """Frames of each generated log."""
    n_cameras: int = 6
    """Cameras of the rig rendered (6 = the full surround rig)."""
    width: int = 320
    """Rendered image width (pixels)."""
    height: int = 180
    """Rendered image height (pixels)."""
    long_side: int = 256
    """Long side of the training images (the network's working resolution)."""
    removal_min_fraction: float = 0.02
    """A view gets a repair pair when its largest agent covers at least this fraction of the image."""
    hole_dilation_px: int = 2
    """The removed agent's mask is grown by this many pixels before inpainting (its soft edge goes too)."""
    inpaint_cycle: tuple[str, ...] = ("fsr_fast", "telea", "ns", "telea")
    """Inpainter of each successive repair pair (FSR is the repair stage's default, and the slowest)."""
    max_eval_depth: float = 80.0
    """Evaluated pixels are non-sky pixels at most this far (m); aligned predictions are clipped to it."""


def world_of(seed: int, config: DepthDataConfig) -> tuple[str, str]:
    """(template, lighting) of the world of ``seed``."""
    return (config.templates[seed % len(config.templates)],
            config.lightings[(seed // len(config.templates)) % len(config.lightings)])


def inverse_depth(depth: np.ndarray) -> np.ndarray:  # [H, W] z-depth (m), 0 = sky -> [H, W] float32 (1/m), 0 = sky
    """1 / depth, with sky (depth 0) at inverse depth 0 (infinitely far)."""
    return np.where(depth > 0, 1.0 / np.maximum(depth, 1e-6), 0.0).astype(np.float32)


def inpaint(rgb: np.ndarray, hole: np.ndarray, method: str) -> np.ndarray:  # [H, W, 3] uint8, [H, W] bool
    """``rgb`` with the ``hole`` pixels filled by one of INPAINT_METHODS."""
    if method not in INPAINT_METHODS:
        raise OmniscsError(f"unknown inpainting method {method!r}; use one of {list(INPAINT_METHODS)}")
    rgb = np.ascontiguousarray(rgb)
    if method == "fsr_fast":
        out = np.zeros_like(rgb)
        cv2.xphoto.inpaint(rgb, np.where(hole, 0, 255).astype(np.uint8), out, cv2.xphoto.INPAINT_FSR_FAST)
        return np.where(hole[..., None], out, rgb)
    flags = cv2.INPAINT_TELEA if method == "telea" else cv2.INPAINT_NS
    return cv2.inpaint(rgb, hole.astype(np.uint8), 3, flags)


def _grow(mask: np.ndarray, px: int) -> np.ndarray:  # [H, W] bool -> [H, W] bool
    if px <= 0:
        return mask
    return cv2.dilate(mask.astype(np.uint8), np.ones((2 * px + 1, 2 * px + 1), np.uint8)).astype(bool)


def rendered_views(seed: int, config: DepthDataConfig) -> Iterator[dict]:
    """Every configured frame and camera of the world of ``seed``: ``rgb`` uint8 [H, W, 3], ``depth`` float32
    [H, W] (m, 0 = sky), ``lighting``; and where one agent covers enough of the view, ``removed_depth`` and
    ``removed_rgb`` (the same view of the world without that agent) and ``agent`` [H, W] bool (its pixels).
    ``config`` is a DepthDataConfig or anything with its world fields (templates ... removal_min_fraction)."""
    if seed < FIRST_DEPTH_SEED:
        raise OmniscsError(f"depth data use seeds >= {FIRST_DEPTH_SEED} (the benchmarks use the lower ones); "
                           f"got {seed}")
    template, lighting = world_of(seed, config)
    world = generate_world(template, int(seed), config.n_frames, config.n_cameras, config.width, config.height,
                           lighting)
    renderer = WorldRenderer(world)
    for frame in config.frames:
        for cam in world.cameras:
            view = renderer.render_camera(frame, cam.name)
            out = {"rgb": view.rgb, "depth": view.depth, "lighting": lighting}
            ids, counts = np.unique(view.instance[view.instance >= 0], return_counts=True)
            if len(ids) and counts.max() >= config.removal_min_fraction * view.instance.size:
                track = int(ids[counts.argmax()])
                without = world.replace(agents=tuple(a for a in world.agents if a.track_id != track))
                removed = WorldRenderer(without).render_camera(frame, cam.name)
                out["removed_depth"], out["removed_rgb"] = removed.depth, removed.rgb
                out["agent"] = view.instance == track
            yield out


def _to_working(image: np.ndarray, size: tuple[int, int], nearest: bool = False) -> np.ndarray:
    h, w = size
    return cv2.resize(image, (w, h), interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_AREA)


def make_training_data(config: DepthDataConfig, progress: Progress = no_progress) -> dict[str, np.ndarray]:
    """Training arrays at the working resolution: ``images`` uint8 [N, h, w, 3], ``inv_depths`` float32 [N, h, w]
    (1/m, 0 = sky) and ``repair`` bool [N] (True for a repair pair: the image's largest agent inpainted, the target
    the inverse depth of the world without it)."""
    size = working_size(config.height, config.width, config.long_side)
    images, targets, repair = [], [], []
    k = 0
    for i, seed in enumerate(config.train_seeds):
        progress(i, len(config.train_seeds), f"depth data: world {seed}")
        for view in rendered_views(seed, config):
            rgb = _to_working(view["rgb"], size)
            images.append(rgb)
            targets.append(_to_working(inverse_depth(view["depth"]), size))
            repair.append(False)
            if "agent" in view:
                hole = _grow(_to_working(view["agent"].astype(np.uint8), size, nearest=True) > 0,
                             config.hole_dilation_px)
                images.append(inpaint(rgb, hole, config.inpaint_cycle[k % len(config.inpaint_cycle)]))
                targets.append(_to_working(inverse_depth(view["removed_depth"]), size))
                repair.append(True)
                k += 1
    progress(len(config.train_seeds), len(config.train_seeds), "depth data: done")
    return {"images": np.stack(images), "inv_depths": np.stack(targets).astype(np.float32),
            "repair": np.array(repair, bool)}


def make_eval_data(config: DepthDataConfig) -> list[dict]:
    """Held-out views at the rendered size: ``rgb``, ``depth``, ``lighting``, and for repair pairs ``inpainted``
    (the largest agent's grown pixels filled), ``removed_depth`` and ``hole`` [H, W] bool."""
    views, k = [], 0
    for seed in config.eval_seeds:
        for view in rendered_views(seed, config):
            if "agent" in view:
                view["hole"] = _grow(view.pop("agent"), config.hole_dilation_px)
                view["inpainted"] = inpaint(view["rgb"], view["hole"],
                                            config.inpaint_cycle[k % len(config.inpaint_cycle)])
                k += 1
            views.append(view)
    return views


# ----------------------------------------------------------------------------- evaluation
def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    ra, rb = rankdata(a), rankdata(b)
    if ra.std() == 0 or rb.std() == 0:
        return 0.0  # a constant map ranks nothing
    return float(np.corrcoef(ra, rb)[0, 1])


def aligned_depth_errors(pred_inv: np.ndarray,  # [H, W] relative inverse depth
                         depth: np.ndarray,     # [H, W] true z-depth (m), 0 = sky
                         max_depth: float,
                         scored: np.ndarray | None = None,  # [H, W] bool: pixels scored (all evaluated ones if None)
                         ) -> dict[str, float] | None:
    """Align ``pred_inv`` to the true inverse depth by least squares (scale >= 0 and shift) over the non-sky pixels
    at most ``max_depth`` away, clip it to that range, and score the resulting depth on ``scored``: AbsRel
    (mean |d - d*| / d*), delta < 1.25 (share of pixels with max(d / d*, d* / d) < 1.25) and Spearman's rank
    correlation of the prediction with the true inverse depth. None when no pixel can be scored."""
    evaluated = (depth > 0) & (depth <= max_depth)
    scored = evaluated if scored is None else scored & evaluated
    if evaluated.sum() < 2 or not scored.any():
        return None
    truth = inverse_depth(depth)
    scale, shift = scale_shift_align(pred_inv, truth, evaluated)
    if scale < 0:  # an output ordered like depth breaks the convention: it gets only the constant fit
        scale, shift = 0.0, float(truth[evaluated].mean())
    aligned = np.maximum(scale * pred_inv.astype(np.float64) + shift, 1.0 / max_depth)
    d, g = 1.0 / aligned[scored], depth[scored].astype(np.float64)
    ratio = np.maximum(d / g, g / d)
    return {"absrel": float(np.mean(np.abs(d - g) / g)), "delta1": float(np.mean(ratio < 1.25)),
            "spearman": _spearman(pred_inv[scored], truth[scored])}


def row_baseline(rgb: np.ndarray) -> np.ndarray:  # [H, W, 3] -> [H, W] float32
    """Inverse depth = rows below the image centre (the horizon of a level camera over flat ground), 0 above."""
    h, w = rgb.shape[:2]
    rows = np.maximum(np.arange(h, dtype=np.float32) - (h - 1) / 2.0, 0.0)
    return np.repeat(rows[:, None], w, 1)


def constant_baseline(rgb: np.ndarray) -> np.ndarray:  # [H, W, 3] -> [H, W] float32
    """The same inverse depth everywhere (after alignment: the image's mean inverse depth)."""
    return np.ones(rgb.shape[:2], np.float32)


def _summary(rows: list[dict]) -> dict:
    if not rows:
        return {"n_images": 0}
    out: dict = {"n_images": len(rows)}
    for key in ("absrel", "delta1", "spearman"):
        values = np.array([r[key] for r in rows])
        out[f"{key}_mean"] = float(values.mean())
        out[f"{key}_median"] = float(np.median(values))
    return out


def evaluate_depth_models(models: dict[str, Callable[[np.ndarray], np.ndarray]], views: list[dict],
                          max_depth: float) -> dict:
    """Per model: whole-image scores over the held-out views (``images``), per lighting, and on the repair pairs
    (``repair_hole``: the inpainted image's prediction, aligned over the whole image to the world without the agent,
    scored inside the hole only)."""
    report = {}
    for name, predict in models.items():
        whole, hole, by_light = [], [], {}
        for view in views:
            scores = aligned_depth_errors(predict(view["rgb"]), view["depth"], max_depth)
            if scores is not None:
                whole.append(scores)
                by_light.setdefault(view["lighting"], []).append(scores)
            if "inpainted" in view:
                scores = aligned_depth_errors(predict(view["inpainted"]), view["removed_depth"], max_depth,
                                              view["hole"])
                if scores is not None:
                    hole.append(scores)
        report[name] = {"images": _summary(whole), "repair_hole": _summary(hole),
                        "by_lighting": {k: _summary(v) for k, v in sorted(by_light.items())}}
    return report


# ----------------------------------------------------------------------------- shipped weights
def _cached_training_data(config: DepthDataConfig, workspace: Path, progress: Progress) -> dict[str, np.ndarray]:
    key = content_hash(DATA_VERSION, asdict(config) | {"eval_seeds": None, "max_eval_depth": None})[:12]
    cache = workspace / "bench-background" / f"reldepth-data-{key}.npz"
    if cache.is_file():  # rendering is most of the data's cost: made once per data configuration
        with np.load(cache, allow_pickle=False) as z:
            return {k: z[k] for k in ("images", "inv_depths", "repair")}
    data = make_training_data(config, progress)
    atomic_write_with(cache, lambda fh: np.savez(fh, **data))
    return data


def _check_data_config(data: DepthDataConfig, config: DepthTrainConfig) -> None:
    if any(s < FIRST_DEPTH_SEED for s in data.train_seeds + data.eval_seeds):
        raise OmniscsError(f"depth data use seeds >= {FIRST_DEPTH_SEED} (the benchmarks use the lower ones)")
    if set(data.train_seeds) & set(data.eval_seeds):
        raise OmniscsError("the held-out seeds of the depth evaluation must not be training seeds")
    if data.long_side != config.architecture.long_side:
        raise OmniscsError(f"the training images' long side ({data.long_side}) must be the network's working "
                           f"resolution ({config.architecture.long_side})")


def export_depth_data(path: Path, workspace: Path | None = None, data: DepthDataConfig = DepthDataConfig(),
                      progress: Progress = no_progress) -> dict:
    """Render (or reuse) the training arrays and write them as a depth pack (omniscs.background.depth_pack) to
    ``path``, to train the network on a machine without the procedural world (``install_trained_depth`` then
    evaluates and installs what it made). Returns the pack's facts."""
    _check_data_config(data, DepthTrainConfig())
    arrays = _cached_training_data(data, workspace_root(workspace), progress)
    size = write_pack(path, arrays["images"], arrays["inv_depths"], arrays["repair"])
    return {"path": str(path), "bytes": size, "n_images": int(len(arrays["images"])),
            "n_repair_pairs": int(arrays["repair"].sum()), "data": asdict(data)}


def train_shipped_depth(workspace: Path | None = None, config: DepthTrainConfig = DepthTrainConfig(),
                        progress: Progress = no_progress, data: DepthDataConfig = DepthDataConfig(),
                        out: Path = SHIPPED, device: str = "cpu") -> dict:
    """Render (or reuse) the training data under the workspace, train the embedded relative-depth network on
    ``device``, evaluate it and two trivial baselines on the held-out worlds, and write its weights and
    ``training.json`` to ``out`` (the shipped ones by default). Returns what training.json holds."""
    _check_data_config(data, config)
    machine = machine_info()
    started = time.perf_counter()
    arrays = _cached_training_data(data, workspace_root(workspace), progress)
    seconds_data = time.perf_counter() - started
    log.info("relative depth: %d training images (%d repair pairs)", len(arrays["images"]), arrays["repair"].sum())
    state, history = train_depth_net(arrays["images"], arrays["inv_depths"], config, progress, device=device)
    info = shipping_info(state, history, data)
    info.update(n_train_images=int(len(arrays["images"])), n_repair_pairs=int(arrays["repair"].sum()),
                seconds_data=seconds_data, seconds_total=time.perf_counter() - started, machine=finish(machine))
    save_depth_net(state, config.architecture, out, info)
    return info


def shipping_info(state: dict, history: dict, data: DepthDataConfig = DepthDataConfig()) -> dict:
    """What training.json holds for weights ``state`` trained with ``history['config']``: the history and the
    evaluation of the weights and the two trivial baselines on the held-out worlds."""
    config = DepthTrainConfig.from_dict(history["config"])
    _check_data_config(data, config)
    started_eval = time.perf_counter()
    net = DepthNet(config.architecture)
    net.load_state_dict(state)
    net.eval()
    views = make_eval_data(data)
    evaluation = evaluate_depth_models(
        {"embedded": lambda rgb: predict_inverse_depth(net, rgb), "baseline_row": row_baseline,
         "baseline_constant": constant_baseline}, views, data.max_eval_depth)
    info = {"command": TRAIN_COMMAND, "data": asdict(data), "data_version": DATA_VERSION, **history,
            "evaluation": {"held_out_seeds": list(data.eval_seeds), "n_views": len(views),
                           "n_repair_pairs": sum("inpainted" in v for v in views),
                           "max_depth_m": data.max_eval_depth,
                           "protocol": "per image, least-squares scale (>= 0) and shift in inverse depth over non-sky "
                                       "pixels at most max_depth_m away, clipped to that range; AbsRel and "
                                       "delta<1.25 of the resulting depth; repair_hole: the inpainted image against "
                                       "the depth of the world without the agent, scored inside the hole",
                           **evaluation},
            "seconds_eval": time.perf_counter() - started_eval}
    return info


def install_trained_depth(folder: Path, data: DepthDataConfig = DepthDataConfig(), out: Path = SHIPPED) -> dict:
    """Evaluate the weights infra/depth_gpu/train.py saved into ``folder`` (``save_depth_net``'s files, its
    training history as the info) on the held-out worlds and write them with that evaluation to ``out``."""
    folder = Path(folder)
    try:
        state = load_file(str(folder / WEIGHTS_FILE))
        history = read_own_json(folder / INFO_FILE, f"{folder} holds no weights from infra/depth_gpu/train.py",
                                expect=dict)
    except (OSError, ValueError) as e:
        raise OmniscsError(f"{folder} holds no weights from infra/depth_gpu/train.py ({type(e).__name__}: {e})") from e
    history.pop("architecture", None)  # save_depth_net's; the configuration in the history names it too
    info = shipping_info(state, history, data)
    info["trained_elsewhere"] = (
        f"trained on {history.get('device_name', history.get('device'))} (torch {history.get('torch')}) by "
        f"infra/depth_gpu/train.py from the pack of `{TRAIN_COMMAND} --export-data PACK`; evaluated and installed "
        f"here with `{TRAIN_COMMAND} --install OUT`")
    info["machine_eval"] = finish(machine_info())
    save_depth_net(state, DepthTrainConfig.from_dict(history["config"]).architecture, out, info)
    return info
