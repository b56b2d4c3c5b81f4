"""Saving and loading traffic-model checkpoints (weights, model config, training record), and where models run."""
from __future__ import annotations

import copy
import hashlib
import json
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from omniscs.errors import OmniscsError
from omniscs.scs.behavior.model import ModelConfig, TrafficModel
from omniscs.storage import atomic_directory, atomic_write_json

WEIGHTS = "model.safetensors"
MODEL_CONFIG = "model_config.json"
TRAINING = "training.json"

#: The checkpoint shipped with the package (trained by ``omniscs scs train-behavior``; see its training.json).
DEFAULT_CHECKPOINT = Path(__file__).parent / "checkpoints" / "default"


def save_checkpoint(model: TrafficModel, out_dir: Path, training: dict, overwrite: bool = False) -> Path:
    """Write weights, model config and the training record (seed, command, data, metrics) atomically."""
    with atomic_directory(Path(out_dir), overwrite=overwrite) as tmp:
        state = {k: v.detach().contiguous().cpu() for k, v in model.state_dict().items()}
        save_file(state, str(tmp / WEIGHTS))
        atomic_write_json(tmp / MODEL_CONFIG, model.config.to_dict())
        atomic_write_json(tmp / TRAINING, training)
    return Path(out_dir)


def load_checkpoint(path: Path | str | None = None) -> TrafficModel:
    """The traffic model in ``path`` (default: the shipped checkpoint), in eval mode."""
    path = Path(path) if path is not None else DEFAULT_CHECKPOINT
    weights, cfg = path / WEIGHTS, path / MODEL_CONFIG
    if not weights.is_file() or not cfg.is_file():
        raise OmniscsError(f"no behaviour-model checkpoint in {path} ({WEIGHTS} and {MODEL_CONFIG} are needed); "
                           "train one with `omniscs scs train-behavior --out DIR` and pass --checkpoint DIR")
    try:
        config = ModelConfig.from_dict(json.loads(cfg.read_text()))
        model = TrafficModel(config)
        model.load_state_dict(load_file(str(weights)))
    except (json.JSONDecodeError, KeyError, TypeError, RuntimeError) as exc:
        raise OmniscsError(f"behaviour-model checkpoint {path} is unreadable or does not match this code "
                           f"({str(exc).splitlines()[0]}); retrain it with `omniscs scs train-behavior`") from None
    model.eval()
    for p in model.parameters():
        p.requires_grad_(False)
    return model


def checkpoint_hash(path: Path | str | None = None) -> str:
    """Content hash of a checkpoint's weights and config (for idempotent reuse of results)."""
    path = Path(path) if path is not None else DEFAULT_CHECKPOINT
    h = hashlib.sha256()
    for name in (WEIGHTS, MODEL_CONFIG):
        h.update((path / name).read_bytes())
    return h.hexdigest()


def training_record(path: Path | str | None = None) -> dict:
    path = Path(path) if path is not None else DEFAULT_CHECKPOINT
    p = path / TRAINING
    return json.loads(p.read_text()) if p.is_file() else {}


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
