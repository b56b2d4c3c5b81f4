"""A fit step's nodes made ready for the rasterizer in one fused pass (CPU): the same maths as ``activate``,
``colors_from_sh`` and ``place_gaussians`` applied node by node, as one Numba kernel with a hand-derived backward
(``_cpu_nodes``). Node by node, those are about forty small PyTorch operations per node each way, and a fit step
renders a dozen nodes: on a 2-core machine their overhead was a sixth of a full-resolution step and more than a
third of a quarter-resolution one (``omniscs bench fit``)."""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from omniscs.devices import keeps_torch_threads
from omniscs.gaussians import LOG_SCALE_RANGE, GaussianParams
from omniscs.nsg import _cpu_nodes as kernels
from omniscs.quaternions import rotmat_to_quat


class _PreparedNodes(torch.autograd.Function):
    """Raw parameters of all nodes, concatenated -> world-frame means, unit quaternions, scales, opacities and
    colours (float32); differentiable in the raw parameters. Node poses and camera centres get no gradient."""

    @staticmethod
    @keeps_torch_threads
    def forward(ctx, means: Tensor, quats: Tensor, log_scales: Tensor, logits: Tensor, sh_dc: Tensor,
                sh_rest: Tensor, node_of: np.ndarray, poses: tuple[np.ndarray, ...], degree: int,
                ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        raw = tuple(np.ascontiguousarray(t.detach().numpy(), dtype=np.float32)
                    for t in (means, quats, log_scales, logits, sh_dc, sh_rest))
        n = means.shape[0]
        out = (np.empty((n, 3), np.float32), np.empty((n, 4), np.float32), np.empty((n, 3), np.float32),
               np.empty(n, np.float32), np.empty((n, 3), np.float32))
        settings = (node_of, *poses, degree, *LOG_SCALE_RANGE)
        kernels.prepare_forward(*raw, *settings, *out)
        ctx.raw, ctx.settings = raw, settings
        return tuple(torch.from_numpy(a) for a in out)

    @staticmethod
    @keeps_torch_threads
    def backward(ctx, *upstream):
        n = ctx.raw[0].shape[0]
        shapes = ((n, 3), (n, 4), (n, 3), (n,), (n, 3))
        v = tuple(np.zeros(shape, np.float32) if g is None else np.ascontiguousarray(g.numpy(), dtype=np.float32)
                  for g, shape in zip(upstream, shapes))
        grads = tuple(np.empty_like(a) for a in ctx.raw)
        kernels.prepare_backward(*ctx.raw, *ctx.settings, *v, *grads)
        return (*(torch.from_numpy(g) for g in grads), None, None, None)


def prepare_nodes(nodes: list[tuple[np.ndarray | None, GaussianParams]],  # (world_from_node [4, 4] or None, raw)
                  camera_centre: np.ndarray,  # [3] world
                  degree: int,
                  ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:  # means, quats, scales, opacities, colours
    """World-frame [N, 3] means, [N, 4] unit quaternions, [N, 3] scales, [N] opacities and [N, 3] colours: every
    node's Gaussians activated, coloured as seen from ``camera_centre`` (SH up to ``degree``, the direction
    taken in the node's frame) and placed in the world by its pose (None: already in the world), concatenated in
    the order given. Float32 CPU parameters; the same values as the node-by-node PyTorch code to float32 rounding."""
    count = len(nodes)
    rotations = np.zeros((count, 3, 3))
    translations = np.zeros((count, 3))
    rotation_quats = np.zeros((count, 4))
    centres = np.zeros((count, 3))
    centre = np.asarray(camera_centre, dtype=np.float64)
    posed = np.zeros(count, dtype=bool)
    for k, (pose, _) in enumerate(nodes):
        if pose is None:
            rotations[k], rotation_quats[k], centres[k] = np.eye(3), (1.0, 0.0, 0.0, 0.0), centre
        else:
            T = np.asarray(pose, dtype=np.float64)
            rotations[k], translations[k], posed[k] = T[:3, :3], T[:3, 3], True
            centres[k] = T[:3, :3].T @ (centre - T[:3, 3])
    if posed.any():
        rotation_quats[posed] = rotmat_to_quat(rotations[posed])  # one call for every node (a fit step has dozens)
    node_of = np.repeat(np.arange(count, dtype=np.int64), [len(p) for _, p in nodes])
    params = [p for _, p in nodes]
    raw = [torch.cat([getattr(p, name) for p in params]) if count > 1 else getattr(params[0], name)
           for name in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")]
    return _PreparedNodes.apply(*raw, node_of, (rotations, translations, rotation_quats, centres), int(degree))
