"""Saving and loading traffic-model checkpoints (weights, model config, training record), and where models run."""
from __future__ import annotations

import copy
import hashlib
from dataclasses import fields
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from omniscs.checks import is_finite, is_int, read_json
from omniscs.errors import OmniscsError
from omniscs.pretrained.registry import folder as shipped_folder, verified_folder
from omniscs.scs.behavior.kinematics import KinematicLimits
from omniscs.scs.behavior.maps import CropSpec
from omniscs.scs.behavior.model import ModelConfig, TrafficModel
from omniscs.storage import atomic_directory, atomic_write_json

WEIGHTS = "model.safetensors"
MODEL_CONFIG = "model_config.json"
TRAINING = "training.json"

#: The checkpoint shipped with the package (registry entry ``behavior``; ``omniscs pretrained train behavior``).
DEFAULT_CHECKPOINT = shipped_folder("behavior")


def save_checkpoint(model: TrafficModel, out_dir: Path, training: dict, overwrite: bool = False) -> Path:
    """Write weights, model config and the training record (seed, command, data, metrics) atomically."""
    with atomic_directory(Path(out_dir), overwrite=overwrite) as tmp:
        state = {k: v.detach().contiguous().cpu() for k, v in model.state_dict().items()}
        save_file(state, str(tmp / WEIGHTS))
        atomic_write_json(tmp / MODEL_CONFIG, model.config.to_dict())
        atomic_write_json(tmp / TRAINING, training)
    return Path(out_dir)


#: Bounds of the architecture fields a checkpoint's config may name (larger is damage, not a model).
MAX_WIDTH = 4096
MAX_STEPS = 10_000
_INT_FIELDS = {"history_steps": MAX_STEPS, "future_steps": MAX_STEPS, "hidden": MAX_WIDTH, "latent": MAX_WIDTH,
               "graph_rounds": 64, "control_knots": MAX_STEPS}
_FLOAT_FIELDS = ("dt", "edge_radius_m", "min_logvar", "max_logvar")
_RETRAIN = "retrain it with `omniscs scs train-behavior`"


def _read_json(path: Path, where: Path):
    return read_json(path, f"the behaviour-model checkpoint {where} is damaged: {_RETRAIN}")


def check_model_config(d, path: Path) -> ModelConfig:
    """A model config from its JSON form, with every field of the right type and within bounds; else one
    OmniscsError naming the file and field (a config is checked before any tensor is allocated)."""
    def bad(field: str, what: str, value):
        text = repr(value)
        raise OmniscsError(f"{path}: field {field} must be {what}; got {text[:60]} ({_RETRAIN})")

    if not isinstance(d, dict):
        raise OmniscsError(f"{path} must be a JSON object of model settings; got a {type(d).__name__} ({_RETRAIN})")
    known = {f.name for f in fields(ModelConfig)}
    unknown = sorted(set(d) - known)
    if unknown:
        raise OmniscsError(f"{path}: unknown field(s) {unknown}; this omniscs's model takes {sorted(known)} "
                           f"({_RETRAIN})")
    for name, bound in _INT_FIELDS.items():
        if name in d and not (is_int(d[name]) and 1 <= d[name] <= bound):
            bad(name, f"an integer from 1 to {bound}", d[name])
    for name in _FLOAT_FIELDS:
        if name in d and not is_finite(d[name]):
            bad(name, "a finite number", d[name])
    for name in ("dt", "edge_radius_m"):
        if d.get(name, 1.0) <= 0:
            bad(name, "a positive number", d[name])
    nested = {"crop": CropSpec, "limits": KinematicLimits}
    args = dict(d)
    for name, cls in nested.items():
        if name not in d:
            continue
        sub = d[name]
        names = {f.name for f in fields(cls)}
        if not isinstance(sub, dict) or set(sub) - names or not all(is_finite(v) for v in sub.values()):
            bad(name, f"an object of finite numbers with fields among {sorted(names)}", sub)
        args[name] = cls(**sub)
    config = ModelConfig(**args)
    rows, cols = config.crop.shape
    if not (0 < config.crop.resolution_m and 1 <= rows <= MAX_WIDTH and 1 <= cols <= MAX_WIDTH):
        bad("crop", f"a patch of 1 to {MAX_WIDTH} cells a side", d.get("crop"))
    return config


def load_traffic_model(path: Path | str | None = None) -> TrafficModel:
    """The traffic model in ``path`` (default: the shipped checkpoint), in eval mode. A missing, damaged or
    mismatched checkpoint is one OmniscsError; the shipped one is hash-checked against the registry first."""
    path = verified_folder(path if path is not None else DEFAULT_CHECKPOINT)
    weights, cfg = path / WEIGHTS, path / MODEL_CONFIG
    if not weights.is_file() or not cfg.is_file():
        raise OmniscsError(f"no behaviour-model checkpoint in {path} ({WEIGHTS} and {MODEL_CONFIG} are needed); "
                           "train one with `omniscs scs train-behavior --out DIR` and pass --checkpoint DIR")
    config = check_model_config(_read_json(cfg, path), cfg)
    try:
        state = load_file(str(weights))
    except Exception as exc:  # safetensors raises its own error type (and OSError) for damaged files
        detail = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:200]
        raise OmniscsError(f"{weights} is not a readable safetensors file ({detail}); the behaviour-model "
                           f"checkpoint {path} is damaged: {_RETRAIN}") from None
    try:
        model = TrafficModel(config)
        model.load_state_dict(state)
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        detail = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:200]
        raise OmniscsError(f"behaviour-model checkpoint {path} is unreadable or does not match this code "
                           f"({detail}); {_RETRAIN}") from None
    model.eval()
    for p in model.parameters():
        p.requires_grad_(False)
    return model



def checkpoint_hash(path: Path | str | None = None) -> str:
    """Content hash of a checkpoint's weights and config (for idempotent reuse of results)."""
    path = Path(path) if path is not None else DEFAULT_CHECKPOINT
    h = hashlib.sha256()
    for name in (WEIGHTS, MODEL_CONFIG):
        try:
            h.update((path / name).read_bytes())
        except OSError as exc:
            raise OmniscsError(f"cannot read {path / name} ({exc.strerror or exc}); pass a behaviour-model "
                               "checkpoint folder (omniscs scs train-behavior --out DIR)") from None
    return h.hexdigest()


def training_record(path: Path | str | None = None) -> dict:
    path = Path(path) if path is not None else DEFAULT_CHECKPOINT
    p = path / TRAINING
    if not p.is_file():
        return {}
    record = _read_json(p, path)
    if not isinstance(record, dict):
        raise OmniscsError(f"{p} must be a JSON object; got a {type(record).__name__} ({_RETRAIN})")
    return record


def set_threads(n: int) -> int:
    """Set torch's intra-op thread count; returns the previous value (to restore)."""
    previous = torch.get_num_threads()
    if n and n > 0:
        torch.set_num_threads(int(n))
    return previous


def model_on(model: TrafficModel, device: torch.device) -> TrafficModel:
    """``model`` itself when its weights are on ``device``, else a copy moved there (the caller's stays put)."""
    current = next(model.parameters()).device
    return model if current == device else copy.deepcopy(model).to(device)
