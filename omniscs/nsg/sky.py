"""The sky node: an environment texture (latitude-longitude, world frame) seen where no Gaussian covers a pixel."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

#: Raw texel values are squashed by a sigmoid; this keeps initial colours away from its flat tails.
SKY_COLOUR_RANGE = (1e-3, 1.0 - 1e-3)


@dataclass(frozen=True)
class SkyParams:
    """Raw sky texture; ``sky_colors`` activates it (sigmoid) and samples it by viewing direction."""

    texture: Tensor  # [3, H, W] logits; rows run from straight up (top) to straight down, columns over azimuth


def init_sky(colour: Tensor,  # [3] in [0, 1]
             height: int, width: int) -> SkyParams:
    c = colour.to(torch.float32).clamp(*SKY_COLOUR_RANGE)
    logits = torch.log(c / (1.0 - c))
    return SkyParams(logits[:, None, None].expand(3, height, width).contiguous())


def sky_colors(sky: SkyParams,
               dirs: Tensor,  # [..., 3] world-frame viewing directions (unit)
               ) -> Tensor:   # [..., 3] colours in [0, 1]
    flat = dirs.reshape(-1, 3)
    azimuth = torch.atan2(flat[:, 1], flat[:, 0]) / math.pi               # [-1, 1]
    elevation = torch.asin(flat[:, 2].clamp(-1.0, 1.0)) / (0.5 * math.pi)  # [-1, 1], +1 = up
    grid = torch.stack([azimuth, -elevation], -1)[None, None]              # [1, 1, M, 2]
    texture = torch.sigmoid(sky.texture)[None]                              # [1, 3, H, W]
    sampled = F.grid_sample(texture, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return sampled[0, :, 0].T.reshape(*dirs.shape[:-1], 3)
