"""The proxy detector's network (``omniscs.eval.detector``): stride-2 blocks, a top-down path back to ``STRIDE``,
a heatmap head and a regression head."""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from omniscs.eval.detector_config import REGRESSION, DetectorConfig


# ----------------------------------------------------------------------------- network
def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, 2, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
                         nn.Conv2d(cout, cout, 3, 1, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


def _conv_bn(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, 1, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class ProxyDetector(nn.Module):
    def __init__(self, config: DetectorConfig = DetectorConfig()) -> None:
        super().__init__()
        self.config = config
        w, h = config.widths, config.head_width
        self.encoder = nn.ModuleList([_block(5, w[0]), _block(w[0], w[1]), _block(w[1], w[2]), _block(w[2], w[3])])
        self.lateral = nn.ModuleList([nn.Conv2d(c, h, 1) for c in (w[1], w[2], w[3])])
        self.fuse = nn.ModuleList([_conv_bn(h, h), _conv_bn(h, h)])
        self.heat_head = nn.Sequential(_conv_bn(h, h), nn.Conv2d(h, len(config.classes), 1))
        self.reg_head = nn.Sequential(_conv_bn(h, h), nn.Conv2d(h, REGRESSION, 1))
        nn.init.constant_(self.heat_head[-1].bias, math.log(config.heatmap_prior / (1 - config.heatmap_prior)))
        with torch.no_grad():
            self.reg_head[-1].bias.zero_()
            self.reg_head[-1].bias[2] = math.log(config.depth_prior_m)
            self.reg_head[-1].bias[7] = 1.0  # cos alpha

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        # images uint8 or float [B, 3, H, W] (0..255) -> heatmap logits [B, C, H/4, W/4],
        # regression [B, REGRESSION, H/4, W/4]
        x = images.float() / 255.0 - 0.5
        b, _, hgt, wid = x.shape
        ys = torch.linspace(-1, 1, hgt, dtype=x.dtype).view(1, 1, hgt, 1).expand(b, 1, hgt, wid)
        xs = torch.linspace(-1, 1, wid, dtype=x.dtype).view(1, 1, 1, wid).expand(b, 1, hgt, wid)
        x = torch.cat([x, xs, ys], 1)
        feats = []
        for block in self.encoder:
            x = block(x)
            feats.append(x)
        top = self.lateral[2](feats[3])
        for level, fuse in ((1, self.fuse[0]), (0, self.fuse[1])):  # stride 8, then stride 4
            skip = feats[level + 1]
            top = fuse(self.lateral[level](skip) + F.interpolate(top, size=skip.shape[-2:], mode="nearest"))
        return self.heat_head(top), self.reg_head(top)


def output_size(config: DetectorConfig) -> tuple[int, int]:
    """(height, width) of the heads' maps."""
    h, w = config.input_height, config.input_width
    for _ in range(2):
        h, w = (h + 1) // 2, (w + 1) // 2
    return h, w


def n_parameters(model: nn.Module) -> int:
    return int(sum(p.numel() for p in model.parameters()))
