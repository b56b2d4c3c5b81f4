"""Relative (monocular) depth for background repair: the interface, the embedded default network and the Depth
Anything adapter (local weights through transformers), and ``load_depth_model`` to pick one by name.

Every model returns affine-invariant inverse depth, as Depth Anything does: one float32 map the size of the input
image, larger = nearer, correct up to an unknown scale > 0 and shift; finite everywhere.
"""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np
import torch

from omniscs.background.depthnet import WEIGHTS_FILE, load_depth_net, predict_inverse_depth
from omniscs.devices import resolve_device
from omniscs.errors import OmniscsError
from omniscs.pretrained.registry import folder as shipped_folder

#: The shipped weights of the embedded network (registry entry ``reldepth``).
SHIPPED = shipped_folder("reldepth")

#: The command that makes the shipped weights (quoted in errors and in training.json).
TRAIN_COMMAND = "omniscs pretrained train reldepth"

SPEC_FORMS = ("None or 'embedded' (the shipped network)",
              "'depth-anything:PATH' (a local folder saved from a Depth Anything checkpoint with transformers)")
"""The model specs load_depth_model accepts, as listed in its error message."""

_DEPTH_ANYTHING_HELP = ("supply a local folder saved from a Depth Anything checkpoint (e.g. "
                        "depth-anything/Depth-Anything-V2-Small-hf, fetched with transformers on a machine with "
                        "network and written with save_pretrained) holding config.json, preprocessor_config.json "
                        "and the weights (model.safetensors)")


@runtime_checkable
class RelativeDepth(Protocol):
    """A monocular relative-depth model."""

    name: str

    def predict(self, rgb: np.ndarray,  # [H, W, 3] uint8
                ) -> np.ndarray:  # [H, W] float32 affine-invariant inverse depth (larger = nearer)
        ...


def check_rgb(rgb: np.ndarray) -> None:
    """Raise an OmniscsError unless ``rgb`` is a uint8 array [H, W, 3] with H, W >= 1."""
    if not isinstance(rgb, np.ndarray):
        raise OmniscsError("relative depth needs an RGB image as a numpy array [H, W, 3] uint8; got "
                           f"{type(rgb).__name__}")
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise OmniscsError(f"relative depth needs an RGB image [H, W, 3]; got an array of shape {rgb.shape}")
    if rgb.dtype != np.uint8:
        raise OmniscsError(f"relative depth needs a uint8 image (0..255); got dtype {rgb.dtype}: convert it first "
                           "(e.g. (x * 255).round().clip(0, 255).astype(np.uint8) for 0..1 floats)")
    if rgb.shape[0] < 1 or rgb.shape[1] < 1:
        raise OmniscsError(f"relative depth needs an image of at least 1x1 pixels; got {rgb.shape[0]}x{rgb.shape[1]}")


class EmbeddedDepth:
    """The embedded network (``omniscs.background.depthnet``), trained here on the procedural world; it runs at its
    working resolution and its output is resized back to the image (bilinear). Deterministic on CPU."""

    name = "embedded"

    def __init__(self, folder: str | Path = SHIPPED, device: str = "cpu") -> None:
        folder = Path(folder)
        if not (folder / WEIGHTS_FILE).is_file():
            raise OmniscsError(f"the embedded relative-depth weights are missing ({folder / WEIGHTS_FILE}); make "
                               f"them with `{TRAIN_COMMAND}`, or use 'depth-anything:PATH' with local weights")
        self.folder = folder
        self.device = resolve_device(device)
        self.net = load_depth_net(folder).to(self.device)

    def predict(self, rgb: np.ndarray) -> np.ndarray:  # [H, W, 3] uint8 -> [H, W] float32

        check_rgb(rgb)
        return predict_inverse_depth(self.net, rgb)


class DepthAnythingDepth:
    """Depth Anything (v1 or v2, any size) through transformers, from a local folder only (never the network):
    the folder's image processor, the model in eval mode, ``predicted_depth`` resized to the image (bilinear)."""

    name = "depth-anything"

    def __init__(self, path: str | Path, device: str = "cpu") -> None:
        try:
            from transformers import AutoImageProcessor, AutoModelForDepthEstimation
        except ImportError:
            raise OmniscsError("Depth Anything needs the transformers package, which is not installed: install it "
                               "(pip install 'omniscs[adapters]' or pip install transformers), or use the embedded "
                               "model (spec 'embedded')") from None
        folder = Path(path).expanduser()
        if not folder.exists():
            raise OmniscsError(f"Depth Anything weights not found: {folder} does not exist; {_DEPTH_ANYTHING_HELP}")
        if not folder.is_dir():
            raise OmniscsError(f"Depth Anything weights must be a folder, but {folder} is a file; "
                               f"{_DEPTH_ANYTHING_HELP}")
        if not (folder / "config.json").is_file():
            raise OmniscsError(f"{folder} has no config.json, so it is not a saved Depth Anything model; "
                               f"{_DEPTH_ANYTHING_HELP}")
        self.device = resolve_device(device)
        try:
            self.processor = AutoImageProcessor.from_pretrained(str(folder), local_files_only=True)
            self.model = AutoModelForDepthEstimation.from_pretrained(str(folder), local_files_only=True,
                                                                     dtype=torch.float32)
        except (OSError, ValueError, KeyError, TypeError, RuntimeError, AttributeError, ImportError) as e:
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise OmniscsError(f"could not load Depth Anything from {folder} ({type(e).__name__}: {first}); "
                               f"{_DEPTH_ANYTHING_HELP}") from e
        self.model = self.model.to(self.device).eval()
        self.path = folder

    @torch.no_grad()
    def predict(self, rgb: np.ndarray) -> np.ndarray:  # [H, W, 3] uint8 -> [H, W] float32
        check_rgb(rgb)
        height, width = rgb.shape[:2]
        inputs = self.processor(images=np.ascontiguousarray(rgb), return_tensors="pt")
        inputs = {k: v.to(self.device) for k, v in inputs.items()}
        depth = self.model(**inputs).predicted_depth  # [1, h, w] relative inverse depth
        depth = torch.nn.functional.interpolate(depth[:, None].float(), size=(height, width), mode="bilinear",
                                                align_corners=False)[0, 0]
        out = depth.cpu().numpy().astype(np.float32)
        if not np.isfinite(out).all():
            raise OmniscsError(f"Depth Anything from {self.path} produced non-finite depth; its weights are damaged "
                               f"or not a depth model: {_DEPTH_ANYTHING_HELP}")
        return out


@lru_cache(maxsize=4)
def _embedded(device: str) -> EmbeddedDepth:
    return EmbeddedDepth(device=device)


def load_depth_model(spec: str | None = None, *, device: str = "cpu") -> RelativeDepth:
    """The relative-depth model ``spec`` names, on ``device``: None or 'embedded' (the shipped network, loaded once
    per process and device) or 'depth-anything:PATH'."""
    if spec is None or spec == "embedded":
        return _embedded(str(device))
    if isinstance(spec, str) and spec.startswith("depth-anything:"):
        path = spec[len("depth-anything:"):]
        if not path:
            raise OmniscsError(f"'depth-anything:' needs a folder after the colon; {_DEPTH_ANYTHING_HELP}")
        return DepthAnythingDepth(path, device=device)
    raise OmniscsError(f"unknown relative-depth model {spec!r}; use one of: {', '.join(SPEC_FORMS)}")
