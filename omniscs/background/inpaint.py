"""2D inpainting for background repair: fill the pixels a removed object covered in one camera image.

The default (OpenCV, classical) needs no weights; LaMa (TorchScript) and diffusers (Stable Diffusion inpainting,
optionally with an inpainting ControlNet as in the OmniSCS paper) are adapters for weights a user has locally.
Every inpainter returns the input unchanged outside the hole: only the masked pixels are ever replaced.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol, runtime_checkable

import cv2
import numpy as np
import torch

from omniscs.background.inpaint_base import HoleFiller, unit_float_to_uint8
from omniscs.background.inpaintnet import SHIPPED, NetInpainter, load_inpaint_net
from omniscs.devices import resolve_device
from omniscs.errors import OmniscsError

OPENCV_METHODS = ("fsr_fast", "fsr_best", "telea", "ns")
"""Classical methods: Fourier-based frequency-selective reconstruction (xphoto FSR, fast and best quality), and
cv2.inpaint's Telea fast marching and Navier-Stokes diffusion."""

LAMA_PAD_MULTIPLE = 8
"""LaMa's encoder downsamples three times, so its input sides are padded up to a multiple of this."""

DIFFUSERS_SIZE_MULTIPLE = 8
"""Stable Diffusion's VAE works on 8x8 pixel cells: the pipeline's height and width are multiples of this."""

SPEC_FORMS = ("None or 'fsr' (the default, OpenCV FSR fast)", "'fsr_fast'", "'fsr_best'", "'telea'", "'ns'",
              "'embedded' (the shipped inpainting network)", "'net:FOLDER' (inpainting network weights saved there)",
              "'lama:PATH' (a TorchScript LaMa file)", "'diffusers:PATH' (a diffusers inpainting pipeline folder)",
              "'diffusers:PATH?controlnet=CN_PATH' (with an inpainting ControlNet folder)")
"""The inpainter specs load_inpainter accepts, as listed in its error message."""


@runtime_checkable
class Inpainter(Protocol):
    """Fills the masked pixels of an image; everything outside the mask comes back byte-identical."""

    @property
    def name(self) -> str:
        """The load_inpainter spec that builds this inpainter (with default settings): for logs and records."""
        ...

    def inpaint(self,
                rgb: np.ndarray,   # [H, W, 3] uint8
                mask: np.ndarray,  # [H, W] bool, True = fill
                ) -> np.ndarray:   # [H, W, 3] uint8, equal to rgb where mask is False
        ...


@dataclass(frozen=True)
class OpenCVInpainter(HoleFiller):
    """Classical inpainting with OpenCV: the embedded default, needs no weights.

    Seconds for one 480x270 image with a 15 % rectangular hole (162x120), textured content, on the 2-core
    development CPU (shared with other work, median of 3): fsr_fast 0.56 s, fsr_best 19.8 s (very slow: meant
    for a few stills, not for every camera of a log), telea 0.024 s, ns 0.022 s. On smooth colour gradients FSR
    continues the gradient 2-5x more accurately than Telea and Navier-Stokes, which diffuse the border colours
    inward (mean error 1.0-1.9 against 4.7-5.5 grey levels on the test image); on noisy texture all four are
    about equal.

    cv2.xphoto.inpaint (FSR) takes a uint8 (or grey) BGR image - float images are refused - and a mask whose
    non-zero pixels are the *known* ones (checked by experiment, as its documentation says); it also moves known
    pixels by up to one grey level, which the composite undoes. cv2.inpaint takes a mask whose non-zero pixels
    are the ones *to fill*. This class converts both from the RGB + fill-mask convention of Inpainter.
    """

    method: str = "fsr_fast"
    """One of OPENCV_METHODS: 'fsr_fast', 'fsr_best' (xphoto FSR), 'telea', 'ns' (cv2.inpaint)."""
    radius: int = 5
    """Neighbourhood radius in pixels that Telea and Navier-Stokes draw each filled pixel from (FSR ignores it)."""

    def __post_init__(self) -> None:
        if self.method not in OPENCV_METHODS:
            raise OmniscsError(f"unknown OpenCV inpainting method {self.method!r}; use one of {list(OPENCV_METHODS)}")
        if isinstance(self.radius, bool) or not isinstance(self.radius, (int, np.integer)) or self.radius < 1:
            raise OmniscsError(f"inpainting radius must be a whole number of pixels >= 1; got {self.radius!r}")

    @property
    def name(self) -> str:
        return self.method

    def _fill(self, rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
        bgr = np.ascontiguousarray(rgb[:, :, ::-1])
        if self.method in ("fsr_fast", "fsr_best"):
            algorithm = cv2.xphoto.INPAINT_FSR_FAST if self.method == "fsr_fast" else cv2.xphoto.INPAINT_FSR_BEST
            known = np.where(mask, 0, 255).astype(np.uint8)
            filled = np.zeros_like(bgr)
            cv2.xphoto.inpaint(bgr, known, filled, algorithm)
        else:
            flags = cv2.INPAINT_TELEA if self.method == "telea" else cv2.INPAINT_NS
            filled = cv2.inpaint(bgr, mask.astype(np.uint8) * 255, int(self.radius), flags)
        return np.ascontiguousarray(filled[:, :, ::-1])


_LAMA_HOW_TO = ("supply a TorchScript LaMa file (e.g. big-lama exported with torch.jit.script/trace and saved "
                "with .save()) that is called as model(image [1, 3, H, W] in [0, 1], mask [1, 1, H, W], 1 = hole)")


@dataclass(frozen=True)
class LamaInpainter(HoleFiller):
    """LaMa (large-mask inpainting, Suvorov et al. 2022) from a local TorchScript export.

    The image goes in as [1, 3, H, W] float in [0, 1] with the hole zeroed (so nothing of the removed object can
    leak into the fill, whatever the export does), the mask as [1, 1, H, W] float with 1 = hole; both are padded
    by reflection to a multiple of LAMA_PAD_MULTIPLE and the output is cropped back and clipped to [0, 1].
    """

    path: str | Path
    """The TorchScript file (e.g. big-lama.pt)."""
    device: str = "cpu"
    """Torch device the model runs on ('cpu', 'cuda', 'cuda:<index>')."""
    _model: Any = field(init=False, repr=False, compare=False)
    """The loaded TorchScript module (set once, in __post_init__)."""

    def __post_init__(self) -> None:
        device = resolve_device(self.device)
        path = Path(self.path)
        if not path.exists():
            raise OmniscsError(f"LaMa model {str(path)!r} does not exist; {_LAMA_HOW_TO}")
        if not path.is_file():
            raise OmniscsError(f"LaMa model {str(path)!r} is not a file; {_LAMA_HOW_TO}")
        try:
            with warnings.catch_warnings():
                # TorchScript is deprecated in recent torch, but it is the format LaMa exports are shared in
                warnings.filterwarnings("ignore", message=r".*torch\.jit.*deprecated")
                model = torch.jit.load(str(path), map_location=device)
        except (RuntimeError, ValueError, OSError) as exc:
            raise OmniscsError(f"LaMa model {str(path)!r} does not load as TorchScript "
                               f"({str(exc).splitlines()[0][:120]}); {_LAMA_HOW_TO}") from None
        model.eval()
        object.__setattr__(self, "_model", model)

    @property
    def name(self) -> str:
        return f"lama:{self.path}"

    def _fill(self, rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
        h, w = mask.shape
        pad = ((0, -h % LAMA_PAD_MULTIPLE), (0, -w % LAMA_PAD_MULTIPLE))
        blanked = rgb.copy()
        blanked[mask] = 0
        image = np.pad(blanked, pad + ((0, 0),), mode="reflect")
        hole = np.pad(mask, pad, mode="reflect")
        device = resolve_device(self.device)
        image_t = torch.from_numpy(image).to(device).permute(2, 0, 1)[None].float() / 255.0  # [1, 3, Hp, Wp]
        hole_t = torch.from_numpy(hole).to(device)[None, None].float()                      # [1, 1, Hp, Wp]
        try:
            with torch.inference_mode():
                out = self._model(image_t, hole_t)
        except (RuntimeError, torch.jit.Error) as exc:  # an error raised inside TorchScript is a torch.jit.Error
            # TorchScript puts its interpreter traceback first and the model's own message last
            reason = ([line.strip() for line in str(exc).splitlines() if line.strip()] or [type(exc).__name__])[-1]
            raise OmniscsError(f"LaMa model {str(self.path)!r} failed on a {image.shape[0]}x{image.shape[1]} input "
                               f"({reason[:160]}); {_LAMA_HOW_TO}") from None
        expected = (1, 3, image.shape[0], image.shape[1])
        if not isinstance(out, torch.Tensor) or tuple(out.shape) != expected:
            got = tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
            raise OmniscsError(f"LaMa model {str(self.path)!r} returned {got}, expected a tensor {expected}; "
                               f"{_LAMA_HOW_TO}")
        filled = out[0, :, :h, :w].permute(1, 2, 0).float().cpu().numpy()
        return unit_float_to_uint8(filled, f"LaMa model {str(self.path)!r}")


_DIFFUSERS_HOW_TO = ("supply a folder written by save_pretrained() from an inpainting checkpoint (e.g. a Stable "
                     "Diffusion inpainting model), downloaded and saved on a machine with network access")


def _nearest_multiple(n: int, multiple: int) -> int:
    """n rounded to the nearest multiple of `multiple`, at least `multiple`."""
    return max(multiple, int(round(n / multiple)) * multiple)


def _resized(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """image [H, W, ...] resized to [height, width, ...]: area averaging when shrinking, bilinear when enlarging."""
    if image.shape[:2] == (height, width):
        return image
    shrinking = height * width < image.shape[0] * image.shape[1]
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR)


@dataclass(frozen=True)
class DiffusersInpainter(HoleFiller):
    """A local diffusers inpainting pipeline (Stable Diffusion inpainting), optionally steered by an inpainting
    ControlNet (the OmniSCS paper repairs backgrounds with ControlNet).

    The image is resized so both sides are multiples of DIFFUSERS_SIZE_MULTIPLE (the pipeline's height and width),
    the hole is resized conservatively (any overlap counts as hole, so no pixel of the removed object is kept), and
    the result is resized back and composited inside exactly the original mask. The ControlNet's control image
    is the image in [0, 1] with the hole's pixels set to -1, the convention of diffusers' ControlNet-inpaint
    examples. Runs are seeded, so the same input gives the same fill.
    """

    path: str | Path
    """Folder written by a diffusers pipeline's save_pretrained (holds model_index.json)."""
    prompt: str = "empty road, street background"
    """What the hole should show."""
    negative_prompt: str = "car, truck, vehicle"
    """What it should not show (the removed object must not come back)."""
    steps: int = 20
    """Denoising steps: more is slower and usually cleaner."""
    guidance_scale: float = 7.5
    """Classifier-free guidance strength (values <= 1 turn guidance off)."""
    seed: int = 0
    """Seed of the torch.Generator for the initial noise."""
    controlnet: str | Path | None = None
    """Folder of an inpainting ControlNet saved with save_pretrained (e.g. control_v11p_sd15_inpaint), or None."""
    device: str = "cpu"
    """Torch device the pipeline runs on ('cpu', 'cuda', 'cuda:<index>')."""
    _pipeline: Any = field(init=False, repr=False, compare=False)
    """The loaded diffusers pipeline (set once, in __post_init__)."""

    def __post_init__(self) -> None:
        if isinstance(self.steps, bool) or not isinstance(self.steps, (int, np.integer)) or self.steps < 1:
            raise OmniscsError(f"diffusers inpainting steps must be a whole number >= 1; got {self.steps!r}")
        if (isinstance(self.guidance_scale, bool) or not isinstance(self.guidance_scale, (int, float, np.number))
                or not math.isfinite(self.guidance_scale) or self.guidance_scale < 0):
            raise OmniscsError(f"diffusers guidance_scale must be a finite number >= 0; got {self.guidance_scale!r}")
        device = resolve_device(self.device)
        folder = Path(self.path)
        if not folder.is_dir():
            raise OmniscsError(f"diffusers pipeline folder {str(folder)!r} does not exist or is not a folder; "
                               f"{_DIFFUSERS_HOW_TO}")
        if not (folder / "model_index.json").is_file():
            raise OmniscsError(f"{str(folder)!r} has no model_index.json, so it is not a saved diffusers pipeline; "
                               f"{_DIFFUSERS_HOW_TO}")
        if self.controlnet is not None and not (Path(self.controlnet) / "config.json").is_file():
            raise OmniscsError(f"ControlNet folder {str(self.controlnet)!r} does not exist or has no config.json; "
                               "supply a folder written by ControlNetModel.save_pretrained() from an inpainting "
                               "ControlNet (e.g. control_v11p_sd15_inpaint), or leave controlnet unset")
        try:
            import diffusers
        except ImportError:
            raise OmniscsError("the diffusers inpainter needs the 'diffusers' and 'transformers' packages; install "
                               "them (pip install diffusers transformers) or use the default inpainter 'fsr'") from None
        try:
            if self.controlnet is None:
                pipeline = diffusers.AutoPipelineForInpainting.from_pretrained(str(folder), local_files_only=True)
            else:
                controlnet = diffusers.ControlNetModel.from_pretrained(str(self.controlnet), local_files_only=True)
                pipeline = diffusers.StableDiffusionControlNetInpaintPipeline.from_pretrained(
                    str(folder), controlnet=controlnet, local_files_only=True)
            pipeline = pipeline.to(device)
        except Exception as exc:  # a foreign folder fails in many library-specific ways; all mean "wrong weights"
            first_line = (str(exc).splitlines() or [type(exc).__name__])[0][:160]
            raise OmniscsError(f"diffusers could not load an inpainting pipeline from {str(folder)!r} "
                               f"({type(exc).__name__}: {first_line}); {_DIFFUSERS_HOW_TO}") from None
        pipeline.set_progress_bar_config(disable=True)
        object.__setattr__(self, "_pipeline", pipeline)

    @property
    def name(self) -> str:
        return f"diffusers:{self.path}" + ("" if self.controlnet is None else f"?controlnet={self.controlnet}")

    def _fill(self, rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
        h, w = mask.shape
        height, width = _nearest_multiple(h, DIFFUSERS_SIZE_MULTIPLE), _nearest_multiple(w, DIFFUSERS_SIZE_MULTIPLE)
        image = _resized(rgb, height, width)
        hole = _resized(mask.astype(np.float32), height, width) > 0.0
        device = resolve_device(self.device)
        image_t = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float() / 255.0  # [1, 3, h, w]
        hole_t = torch.from_numpy(hole)[None, None].float()                                            # [1, 1, h, w]
        inputs: dict[str, Any] = dict(
            prompt=self.prompt, negative_prompt=self.negative_prompt, image=image_t, mask_image=hole_t,
            height=height, width=width, num_inference_steps=int(self.steps), guidance_scale=float(self.guidance_scale),
            generator=torch.Generator(device=device).manual_seed(int(self.seed)), output_type="np")
        if self.controlnet is not None:
            control = image_t.clone()
            control[hole_t.expand_as(control) > 0.5] = -1.0
            inputs["control_image"] = control
        result = self._pipeline(**inputs)
        if any(getattr(result, "nsfw_content_detected", None) or []):
            raise OmniscsError(f"the safety checker of {str(self.path)!r} blanked the inpainted image; change the "
                               "prompt, or save the pipeline without a safety checker (safety_checker=None)")
        generated = np.asarray(result.images[0], dtype=np.float32)  # [height, width, 3] in [0, 1]
        if generated.shape != (height, width, 3):
            raise OmniscsError(f"diffusers pipeline {str(self.path)!r} returned {generated.shape}, expected "
                               f"{(height, width, 3)}; {_DIFFUSERS_HOW_TO}")
        return unit_float_to_uint8(_resized(generated, h, w), f"diffusers pipeline {str(self.path)!r}")


def load_inpainter(spec: str | None = None, *, device: str = "cpu") -> Inpainter:
    """The inpainter a spec names (see SPEC_FORMS): None or 'fsr' is the default OpenCV FSR fast;
    'fsr_fast', 'fsr_best', 'telea', 'ns' pick an OpenCV method; 'embedded' is the shipped inpainting network
    (omniscs.background.inpaintnet) and 'net:FOLDER' the same network with weights saved there; 'lama:PATH' loads a TorchScript LaMa file;
    'diffusers:PATH' a saved diffusers inpainting pipeline, and 'diffusers:PATH?controlnet=CN_PATH' the same
    steered by an inpainting ControlNet. `device` is where weight-based models run."""
    if spec is None or spec == "fsr":
        return OpenCVInpainter("fsr_fast")
    if not isinstance(spec, str):
        raise OmniscsError(f"an inpainter spec must be a string; got {type(spec).__name__}; use one of "
                           f"{', '.join(SPEC_FORMS)}")
    if spec in OPENCV_METHODS:
        return OpenCVInpainter(spec)
    if spec == "embedded":
        return _network_inpainter(None, device)
    kind, sep, rest = spec.partition(":")
    builders: dict[str, Callable[[str], Inpainter]] = {
        "net": lambda folder: _network_inpainter(folder, device),
        "lama": lambda path: LamaInpainter(path, device=device),
        "diffusers": lambda target: _diffusers_from_spec(target, device),
    }
    if sep and kind in builders and rest:
        return builders[kind](rest)
    raise OmniscsError(f"unknown inpainter spec {spec!r}; use one of {', '.join(SPEC_FORMS)}")


def _network_inpainter(folder: str | None, device: str) -> Inpainter:
    """The embedded inpainting network from the shipped weights (folder None) or another folder of them."""
    return NetInpainter(load_inpaint_net(SHIPPED if folder is None else folder),
                        "embedded" if folder is None else f"net:{folder}", resolve_device(device))


def _diffusers_from_spec(target: str, device: str) -> DiffusersInpainter:
    """'PATH' or 'PATH?controlnet=CN_PATH' (the part after 'diffusers:') as a DiffusersInpainter."""
    path, sep, query = target.partition("?")
    if not sep:
        return DiffusersInpainter(path, device=device)
    key, _, controlnet = query.partition("=")
    if key != "controlnet" or not controlnet or not path:
        raise OmniscsError(f"cannot read the diffusers spec 'diffusers:{target}'; write 'diffusers:PATH' or "
                           "'diffusers:PATH?controlnet=CN_PATH'")
    return DiffusersInpainter(path, controlnet=controlnet, device=device)

