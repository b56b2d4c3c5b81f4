"""2D inpainting: the OpenCV default fills smooth images well and never touches known pixels; the LaMa and
diffusers adapters run real (tiny, locally built) models and refuse clearly when weights are missing."""
from __future__ import annotations

import json
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from omniscs.background.inpaint import (OPENCV_METHODS, DiffusersInpainter, Inpainter, LamaInpainter,
                                        OpenCVInpainter, load_inpainter)
from omniscs.errors import OmniscsError

# Mean absolute error (0..255) inside the hole of the smooth test image, measured per method with margin
# (measured: telea 5.5, ns 4.7, fsr_fast 1.9, fsr_best 1.0; filling with zeros gives 120, with the mean colour 12.6).
SMOOTH_FILL_MAE_BOUND = {"telea": 9.0, "ns": 9.0, "fsr_fast": 4.0, "fsr_best": 3.0}


def smooth_image(height: int = 48, width: int = 64) -> np.ndarray:  # [H, W, 3] uint8
    """Horizontal + vertical colour gradients: what a classical inpainter should continue exactly."""
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    u, v = xx / (width - 1), yy / (height - 1)
    return np.stack([40 + 160 * u, 30 + 180 * v, 60 + 60 * (u + v)], axis=-1).round().astype(np.uint8)


def box_mask(height: int, width: int, top: int, left: int, bottom: int, right: int) -> np.ndarray:  # [H, W] bool
    mask = np.zeros((height, width), dtype=bool)
    mask[top:bottom, left:right] = True
    return mask


def noisy_image(height: int, width: int, seed: int = 0) -> np.ndarray:  # [H, W, 3] uint8
    return np.random.default_rng(seed).integers(0, 256, (height, width, 3), dtype=np.uint8)


def hole_mae(filled: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    return float(np.abs(filled[mask].astype(np.float64) - truth[mask]).mean())


# ---------------------------------------------------------------------------------------------- OpenCV default

@pytest.mark.parametrize("method", OPENCV_METHODS)
def test_opencv_methods_keep_every_known_pixel_byte_identical(method):
    rgb = noisy_image(40, 56)
    mask = box_mask(40, 56, 10, 12, 30, 40)
    out = OpenCVInpainter(method).inpaint(rgb, mask)
    assert out.shape == rgb.shape and out.dtype == np.uint8
    assert np.array_equal(out[~mask], rgb[~mask])


@pytest.mark.parametrize("method", OPENCV_METHODS)
def test_opencv_methods_continue_a_smooth_gradient_into_the_hole(method):
    truth = smooth_image()
    mask = box_mask(*truth.shape[:2], 16, 20, 32, 44)
    damaged = truth.copy()
    damaged[mask] = (0, 0, 255)  # the removed object's colour
    out = OpenCVInpainter(method).inpaint(damaged, mask)
    assert hole_mae(out, truth, mask) < SMOOTH_FILL_MAE_BOUND[method]


def test_smooth_fill_bound_rejects_a_zero_fill_and_a_mean_colour_fill():
    truth = smooth_image()
    mask = box_mask(*truth.shape[:2], 16, 20, 32, 44)
    zero_filled = truth.copy()
    zero_filled[mask] = 0
    mean_filled = truth.copy()
    mean_filled[mask] = truth[~mask].mean(axis=0).round().astype(np.uint8)
    loosest = max(SMOOTH_FILL_MAE_BOUND.values())
    assert hole_mae(zero_filled, truth, mask) > loosest
    assert hole_mae(mean_filled, truth, mask) > loosest


@pytest.mark.parametrize("method", OPENCV_METHODS)
def test_opencv_fill_does_not_depend_on_what_the_hole_showed(method):
    rgb = smooth_image()
    mask = box_mask(*rgb.shape[:2], 16, 20, 32, 44)
    black, white = rgb.copy(), rgb.copy()
    black[mask], white[mask] = 0, 255
    inpainter = OpenCVInpainter(method)
    assert np.array_equal(inpainter.inpaint(black, mask), inpainter.inpaint(white, mask))


def test_default_spec_is_fsr_fast_and_every_method_has_a_spec():
    assert load_inpainter().name == "fsr_fast" and load_inpainter("fsr").name == "fsr_fast"
    for method in OPENCV_METHODS:
        inpainter = load_inpainter(method)
        assert isinstance(inpainter, Inpainter) and inpainter == OpenCVInpainter(method)
        assert load_inpainter(inpainter.name) == inpainter


@pytest.mark.parametrize("kwargs", [{"method": "shiftmap"}, {"radius": 0}, {"radius": 2.5}])
def test_opencv_inpainter_refuses_unknown_settings(kwargs):
    with pytest.raises(OmniscsError):
        OpenCVInpainter(**kwargs)


# ---------------------------------------------------------------------------------------------- shared contract

def test_empty_mask_returns_an_equal_copy_without_filling():
    rgb = noisy_image(20, 30)
    out = OpenCVInpainter().inpaint(rgb, np.zeros((20, 30), dtype=bool))
    assert out is not rgb and np.array_equal(out, rgb)
    out[0, 0] = 255 - out[0, 0]
    assert not np.array_equal(out, rgb)  # a copy, not a view


def test_a_mask_over_every_pixel_is_an_error():
    with pytest.raises(OmniscsError, match="nothing to inpaint from"):
        OpenCVInpainter().inpaint(noisy_image(20, 30), np.ones((20, 30), dtype=bool))


@pytest.mark.parametrize("rgb, mask", [
    (np.zeros((20, 30), np.uint8), np.zeros((20, 30), bool)),          # grey image
    (np.zeros((20, 30, 4), np.uint8), np.zeros((20, 30), bool)),       # RGBA
    (np.zeros((20, 30, 3), np.float32), np.zeros((20, 30), bool)),     # float image
    (np.zeros((0, 30, 3), np.uint8), np.zeros((0, 30), bool)),         # empty image
    ([[[0, 0, 0]]], np.zeros((1, 1), bool)),                            # not an array
    (np.zeros((20, 30, 3), np.uint8), np.zeros((20, 30), np.uint8)),   # 0/1 mask, not bool
    (np.zeros((20, 30, 3), np.uint8), np.zeros((20, 30, 1), bool)),    # mask with a channel axis
    (np.zeros((20, 30, 3), np.uint8), np.zeros((30, 20), bool)),       # transposed mask
])
def test_wrong_shapes_and_dtypes_are_domain_errors(rgb, mask):
    with pytest.raises(OmniscsError):
        OpenCVInpainter().inpaint(rgb, mask)


@pytest.mark.parametrize("spec", ["", "FSR", "lama", "lama:", "diffusers:", "sd:/x", "fsr_fast:x",
                                  "diffusers:/x?lora=y"])
def test_unknown_specs_are_refused_with_the_accepted_forms(spec):
    with pytest.raises(OmniscsError, match="diffusers:PATH"):
        load_inpainter(spec)


# ---------------------------------------------------------------------------------------------- LaMa adapter

class MeanColourFill(nn.Module):
    """LaMa's call signature; fills the hole with the mean colour of the known pixels. Refuses inputs whose
    sides are not multiples of 8 (LaMa's requirement) or masks that are not {0, 1}."""

    def forward(self, image: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        if image.shape[2] % 8 != 0 or image.shape[3] % 8 != 0:
            raise RuntimeError("input is not padded to a multiple of 8")
        if bool(((mask != 0) & (mask != 1)).any()):
            raise RuntimeError("mask is not {0, 1}")
        known = 1.0 - mask
        mean = (image * known).sum(dim=(2, 3), keepdim=True) / known.sum(dim=(2, 3), keepdim=True)
        return image * known + mean * mask


class Echo(nn.Module):
    """Returns the image it is given: shows what the adapter lets the model see."""

    def forward(self, image: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        return image


class DropsARow(nn.Module):
    """A model whose output does not have its input's size."""

    def forward(self, image: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        return image[:, :, 1:, :]


class ReturnsNaN(nn.Module):
    def forward(self, image: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        return image * float("nan")


class FailsInside(nn.Module):
    """A model that raises while running (inside TorchScript that surfaces as torch.jit.Error)."""

    def forward(self, image: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        raise RuntimeError("broken export")


def save_torchscript(module: nn.Module, path: Path) -> Path:
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r".*torch\.jit.*deprecated")
        torch.jit.script(module).save(str(path))
    return path


@pytest.mark.parametrize("height, width", [(32, 48), (37, 51), (5, 3)])
def test_lama_adapter_pads_fills_and_composites(tmp_path, height, width):
    path = save_torchscript(MeanColourFill(), tmp_path / "lama.pt")
    inpainter = load_inpainter(f"lama:{path}")
    assert isinstance(inpainter, LamaInpainter) and inpainter.name == f"lama:{path}"
    rgb = np.empty((height, width, 3), dtype=np.uint8)
    rgb[:] = (200, 40, 90)
    mask = np.zeros((height, width), dtype=bool)
    mask[height // 3: height // 3 + max(1, height // 3), width // 4: width // 4 + max(1, width // 2)] = True
    rgb[mask] = (0, 0, 255)  # the removed object
    out = inpainter.inpaint(rgb, mask)
    assert out.shape == rgb.shape and out.dtype == np.uint8
    assert np.array_equal(out[~mask], rgb[~mask])
    assert np.abs(out[mask].astype(int) - (200, 40, 90)).max() <= 1


def test_lama_adapter_keeps_known_pixels_exact_on_a_textured_image(tmp_path):
    inpainter = LamaInpainter(save_torchscript(MeanColourFill(), tmp_path / "lama.pt"))
    rgb = noisy_image(37, 51, seed=3)
    mask = box_mask(37, 51, 5, 7, 20, 30)
    out = inpainter.inpaint(rgb, mask)
    assert np.array_equal(out[~mask], rgb[~mask])
    # the reflected padding is known too, so the model's mean colour shifts a little
    assert np.abs(out[mask].astype(float) - rgb[~mask].mean(axis=0)).max() < 6.0


def test_lama_model_never_sees_the_removed_object(tmp_path):
    inpainter = LamaInpainter(save_torchscript(Echo(), tmp_path / "echo.pt"))
    rgb = noisy_image(24, 40)
    mask = box_mask(24, 40, 4, 4, 12, 20)
    assert (inpainter.inpaint(rgb, mask)[mask] == 0).all()


def test_lama_refuses_a_missing_path_a_folder_and_a_file_that_is_not_torchscript(tmp_path):
    with pytest.raises(OmniscsError, match="does not exist.*TorchScript"):
        load_inpainter(f"lama:{tmp_path / 'big-lama.pt'}")
    with pytest.raises(OmniscsError, match="not a file"):
        LamaInpainter(tmp_path)
    (tmp_path / "notes.txt").write_text("not a model")
    with pytest.raises(OmniscsError, match="does not load as TorchScript"):
        LamaInpainter(tmp_path / "notes.txt")
    torch.save({"weight": torch.zeros(3)}, tmp_path / "state_dict.pt")
    with pytest.raises(OmniscsError, match="does not load as TorchScript"):
        LamaInpainter(tmp_path / "state_dict.pt")


@pytest.mark.parametrize("module, message", [(DropsARow(), "expected a tensor"), (ReturnsNaN(), "NaN or Inf"),
                                             (FailsInside(), "failed on a 16x16 input")])
def test_lama_refuses_wrong_or_failing_models_with_a_domain_error(tmp_path, module, message):
    inpainter = LamaInpainter(save_torchscript(module, tmp_path / "bad.pt"))
    with pytest.raises(OmniscsError, match=message):
        inpainter.inpaint(noisy_image(16, 16), box_mask(16, 16, 4, 4, 8, 8))


# ---------------------------------------------------------------------------------------------- diffusers adapter

def write_byte_level_clip_tokenizer_files(folder: Path) -> tuple[Path, Path]:
    """vocab.json + merges.txt for a CLIP tokenizer over single byte-level symbols (no merges)."""
    printable = [*range(ord("!"), ord("~") + 1), *range(ord("¡"), ord("¬") + 1), *range(ord("®"), ord("ÿ") + 1)]
    extra = [b for b in range(256) if b not in printable]
    symbols = [chr(c) for c in printable] + [chr(256 + i) for i in range(len(extra))]
    tokens = ["<|startoftext|>", "<|endoftext|>"] + symbols + [s + "</w>" for s in symbols]
    vocab, merges = folder / "vocab.json", folder / "merges.txt"
    vocab.write_text(json.dumps({t: i for i, t in enumerate(tokens)}))
    merges.write_text("#version: 0.2\n")
    return vocab, merges


@pytest.fixture(scope="module")
def tiny_diffusers(tmp_path_factory) -> tuple[Path, Path]:
    """A Stable Diffusion inpainting pipeline and an inpainting ControlNet with random weights, a few MB, saved
    with save_pretrained: (pipeline folder, controlnet folder)."""
    diffusers = pytest.importorskip("diffusers")
    transformers = pytest.importorskip("transformers")
    root = tmp_path_factory.mktemp("tiny_diffusers")
    torch.manual_seed(0)
    vocab, merges = write_byte_level_clip_tokenizer_files(root)
    tokenizer = transformers.CLIPTokenizer(str(vocab), str(merges), model_max_length=77)
    text_encoder = transformers.CLIPTextModel(transformers.CLIPTextConfig(
        vocab_size=tokenizer.vocab_size, hidden_size=32, intermediate_size=37, num_attention_heads=4,
        num_hidden_layers=2, max_position_embeddings=77, projection_dim=32, bos_token_id=0, eos_token_id=1,
        pad_token_id=1))
    blocks = dict(block_out_channels=(32, 64), layers_per_block=1, norm_num_groups=8, cross_attention_dim=32,
                  attention_head_dim=4, down_block_types=("DownBlock2D", "CrossAttnDownBlock2D"))
    unet = diffusers.UNet2DConditionModel(in_channels=9, out_channels=4, sample_size=32,
                                          up_block_types=("CrossAttnUpBlock2D", "UpBlock2D"), **blocks)
    vae = diffusers.AutoencoderKL(block_out_channels=(32, 64), in_channels=3, out_channels=3, latent_channels=4,
                                  down_block_types=("DownEncoderBlock2D",) * 2,
                                  up_block_types=("UpDecoderBlock2D",) * 2,
                                  norm_num_groups=8, sample_size=64)
    scheduler = diffusers.DDIMScheduler(beta_start=0.000_85, beta_end=0.012, beta_schedule="scaled_linear",
                                        clip_sample=False, set_alpha_to_one=False, steps_offset=1)
    pipeline = diffusers.StableDiffusionInpaintPipeline(vae=vae, text_encoder=text_encoder, tokenizer=tokenizer,
                                                        unet=unet, scheduler=scheduler, safety_checker=None,
                                                        feature_extractor=None, requires_safety_checker=False)
    pipeline.save_pretrained(root / "pipeline")
    # the VAE above halves the resolution, so the control image is embedded with one downsampling too
    controlnet = diffusers.ControlNetModel(in_channels=4, conditioning_embedding_out_channels=(16, 32), **blocks)
    controlnet.save_pretrained(root / "controlnet")
    return root / "pipeline", root / "controlnet"


@pytest.mark.slow
def test_diffusers_adapter_runs_a_saved_inpainting_pipeline(tiny_diffusers):
    folder, _ = tiny_diffusers
    inpainter = load_inpainter(f"diffusers:{folder}")
    assert isinstance(inpainter, DiffusersInpainter) and inpainter.name == f"diffusers:{folder}"
    inpainter = DiffusersInpainter(folder, steps=2)
    rgb = noisy_image(64, 64)
    mask = box_mask(64, 64, 20, 16, 44, 40)
    out = inpainter.inpaint(rgb, mask)
    assert out.shape == rgb.shape and out.dtype == np.uint8
    assert np.array_equal(out[~mask], rgb[~mask])
    assert np.array_equal(inpainter.inpaint(rgb, mask), out)  # seeded


@pytest.mark.slow
def test_diffusers_adapter_resizes_sizes_that_are_not_multiples_of_8(tiny_diffusers):
    inpainter = DiffusersInpainter(tiny_diffusers[0], steps=2)
    rgb = noisy_image(45, 70)
    mask = box_mask(45, 70, 1, 60, 2, 61)  # a one-pixel hole survives the resize
    out = inpainter.inpaint(rgb, mask)
    assert out.shape == rgb.shape and np.array_equal(out[~mask], rgb[~mask])


@pytest.mark.slow
def test_diffusers_adapter_with_an_inpainting_controlnet(tiny_diffusers):
    folder, controlnet = tiny_diffusers
    loaded = load_inpainter(f"diffusers:{folder}?controlnet={controlnet}")
    assert isinstance(loaded, DiffusersInpainter) and loaded.name == f"diffusers:{folder}?controlnet={controlnet}"
    inpainter = DiffusersInpainter(folder, controlnet=controlnet, steps=2)
    rgb = noisy_image(64, 48)
    mask = box_mask(64, 48, 10, 10, 30, 30)
    out = inpainter.inpaint(rgb, mask)
    assert out.shape == rgb.shape and np.array_equal(out[~mask], rgb[~mask])


class RecordingPipeline:
    """Stands in for a loaded pipeline: records its inputs and returns mid-grey."""

    def __init__(self) -> None:
        self.inputs: dict = {}

    def __call__(self, **inputs):
        self.inputs = inputs
        images = np.full((1, inputs["height"], inputs["width"], 3), 0.5, dtype=np.float32)
        return type("Output", (), {"images": images, "nsfw_content_detected": None})()


@pytest.mark.slow
def test_controlnet_control_image_marks_the_hole_with_minus_one(tiny_diffusers):
    folder, controlnet = tiny_diffusers
    inpainter = DiffusersInpainter(folder, controlnet=controlnet, steps=2, seed=7)
    recorder = RecordingPipeline()
    object.__setattr__(inpainter, "_pipeline", recorder)
    rgb = noisy_image(32, 40)
    mask = box_mask(32, 40, 8, 8, 16, 24)
    out = inpainter.inpaint(rgb, mask)
    control, image, hole = (recorder.inputs[k] for k in ("control_image", "image", "mask_image"))
    assert control.shape == (1, 3, 32, 40) and hole.shape == (1, 1, 32, 40)
    assert torch.equal(hole[0, 0] > 0.5, torch.from_numpy(mask))
    assert (control[0][:, torch.from_numpy(mask)] == -1.0).all()
    assert torch.equal(control[0][:, ~torch.from_numpy(mask)], image[0][:, ~torch.from_numpy(mask)])
    assert recorder.inputs["generator"].initial_seed() == 7 and recorder.inputs["num_inference_steps"] == 2
    assert (out[mask] == 128).all() and np.array_equal(out[~mask], rgb[~mask])


def test_diffusers_refuses_a_missing_folder_and_one_without_model_index(tmp_path):
    with pytest.raises(OmniscsError, match="does not exist.*save_pretrained"):
        load_inpainter(f"diffusers:{tmp_path / 'sd-inpainting'}")
    with pytest.raises(OmniscsError, match="no model_index.json.*save_pretrained"):
        DiffusersInpainter(tmp_path)


def test_diffusers_refuses_a_folder_it_cannot_load(tmp_path):
    (tmp_path / "model_index.json").write_text(json.dumps({"_class_name": "StableDiffusionInpaintPipeline",
                                                           "unet": ["diffusers", "UNet2DConditionModel"]}))
    with pytest.raises(OmniscsError, match="could not load an inpainting pipeline.*save_pretrained"):
        DiffusersInpainter(tmp_path)


@pytest.mark.slow
def test_diffusers_refuses_a_missing_controlnet_folder(tiny_diffusers, tmp_path):
    with pytest.raises(OmniscsError, match="ControlNet folder"):
        load_inpainter(f"diffusers:{tiny_diffusers[0]}?controlnet={tmp_path / 'cn'}")


def test_diffusers_refuses_clearly_when_the_package_is_missing(tmp_path, monkeypatch):
    (tmp_path / "model_index.json").write_text("{}")
    monkeypatch.setitem(sys.modules, "diffusers", None)  # makes `import diffusers` raise ImportError
    with pytest.raises(OmniscsError, match="needs the 'diffusers'"):
        DiffusersInpainter(tmp_path)
