"""A track's node alone and the pixels it shares with the log: what the colour correction of the dual strategy
(``agents.dual``) and the relighting of pool models (``agents.relight``) both fit on."""
from __future__ import annotations

import cv2
import numpy as np
import torch

from omniscs.gaussians import GaussianParams, empty_params
from omniscs.nsg.graph import SceneGraph, render_view

#: Pixels a shared mask is eroded by on each side (a (2k+1)-square kernel), so no background colour leaks in.
SHARED_MASK_EROSION_PX = 2
#: Views whose shared mask keeps fewer pixels than this are left out.
MIN_SHARED_PIXELS = 20


def track_alone(graph: SceneGraph, track_id: int, params: GaussianParams) -> SceneGraph:
    """The graph holding only the track's node (with ``params``), no background, no exposure correction."""
    node = graph.agent(track_id).with_changes(gaussians=params)
    return graph.replace(background=empty_params(graph.sh_degree).to(graph.device), agents=(node,), exposure={})


def shared_masks(alone: SceneGraph, samples: list[tuple]) -> list[tuple]:
    """Per colour sample (``dual.colour_samples``), the pixels both the fitted track (weight > 0.9) and the candidate
    (``alone``: the graph holding only its node, ``track_alone``) cover, eroded by 2 pixels so that no background
    colour leaks onto the model's rim: (view, target, mask) where at least 20 pixels remain."""
    side = 2 * SHARED_MASK_EROSION_PX + 1
    kernel = np.ones((side, side), np.uint8)
    out = []
    with torch.no_grad():
        for view, target, weight in samples:
            covered = render_view(alone, view).alpha.cpu().numpy() > 0.9
            shared = cv2.erode(((weight.numpy() > 0.9) & covered).astype(np.uint8), kernel) > 0
            if shared.sum() >= MIN_SHARED_PIXELS:
                out.append((view, target, torch.from_numpy(shared)))
    return out
