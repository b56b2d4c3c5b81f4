"""The compute device a model config names, checked once for every model package."""
from __future__ import annotations

import torch

from omniscs.errors import OmniscsError


def resolve_device(name: str | torch.device) -> torch.device:
    """The torch device called ``name`` ('cpu', 'cuda', 'cuda:<index>'), or an OmniscsError saying why it
    cannot be used here (an unknown name, or CUDA asked for on a machine without it)."""
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError):
        raise OmniscsError(f"unknown device {name!r}; use 'cpu' or 'cuda' (or 'cuda:<index>')") from None
    if device.type not in ("cpu", "cuda"):
        raise OmniscsError(f"device {name!r} is not supported; use 'cpu' or 'cuda' (or 'cuda:<index>')")
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise OmniscsError(f"device {name!r} was asked for, but torch sees no CUDA GPU here (no CUDA device: "
                               "torch.cuda.is_available() is False); use device='cpu', or run on a machine with "
                               "a GPU and a CUDA build of torch")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise OmniscsError(f"device {name!r} does not exist: torch sees {torch.cuda.device_count()} CUDA "
                               f"GPU(s); use 'cuda:0' .. 'cuda:{torch.cuda.device_count() - 1}'")
    return device
