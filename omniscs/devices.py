"""The compute device a model config names, checked once for every model package; torch's CPU threads around
the Numba kernels."""
from __future__ import annotations

import functools
from typing import Callable, TypeVar

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


F = TypeVar("F", bound=Callable)


def keeps_torch_threads(fn: F) -> F:
    """``fn`` (which launches Numba parallel kernels), leaving torch's intra-op thread count as it found it.

    Numba's OpenMP layer sets the calling thread's OpenMP thread count to Numba's own at every parallel launch,
    and torch reads its thread count from that same setting: after one kernel, a fit that asked torch for one
    thread (``FitConfig.torch_threads``) ran its small per-step tensor operations on two, with threads waking up
    for every Adam group (measured: Adam 0.26 -> 3.3 ms a step at the scale-out setting).
    """
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        threads = torch.get_num_threads()
        try:
            return fn(*args, **kwargs)
        finally:
            if torch.get_num_threads() != threads:
                torch.set_num_threads(threads)
    return wrapper  # type: ignore[return-value]
