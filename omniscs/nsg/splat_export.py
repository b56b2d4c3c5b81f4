"""A fitted (and edited) scene graph at one frame as standard 3D Gaussian splatting PLY files (the INRIA layout the
pool's models are written in, ``omniscs.agents.ply``), for splat viewers (SuperSplat, viser, the original viewer).

Every node goes into the world frame of the scene: the background as fitted, each agent present in the frame moved
by its pose at that frame, its view-dependent colours turned with it (``gaussians.rigidly_moved``), so a viewer that
evaluates the SH in the world frame sees what our renderer shows. The sky (a texture at infinity) and the per-camera
exposure correction are not Gaussians and are not written; agents with relight data are written with the colours
their Gaussians hold (unlit)."""
from __future__ import annotations

from pathlib import Path

from omniscs.agents.ply import write_gaussian_ply
from omniscs.errors import OmniscsError
from omniscs.gaussians import GaussianParams, concat_params, rigidly_moved, with_sh_degree
from omniscs.nsg.graph import BACKGROUND, SceneGraph, agent_key
from omniscs.storage import atomic_directory


def frame_gaussians(graph: SceneGraph, frame: int) -> dict[str, GaussianParams]:
    """{node key: its Gaussians in the world frame at ``frame``}: the background and every agent present then (an
    out-of-range frame is one OmniscsError); all with the graph's SH degree."""
    if not isinstance(frame, int) or isinstance(frame, bool) or not 0 <= frame < graph.n_frames:
        raise OmniscsError(f"frame {frame!r} is out of range: the scene graph of {graph.scene_id} has frames 0 to "
                           f"{graph.n_frames - 1}")
    degree = graph.sh_degree
    out = {BACKGROUND: with_sh_degree(graph.background.detached(), degree)}
    for agent in graph.agents:
        if not agent.present[frame] or len(agent.gaussians) == 0:
            continue
        T = agent.world_from_agent[frame]
        out[agent_key(agent.track_id)] = with_sh_degree(rigidly_moved(agent.gaussians.detached(), T[:3, :3].copy(),
                                                                      T[:3, 3].copy()),
                                                        degree)
    return out


def write_scene_ply(graph: SceneGraph, frame: int, out: str | Path, split: bool = False,
                    overwrite: bool = False) -> list[Path]:
    """Write the graph at ``frame`` as one PLY file ``out`` (every node together) or, with ``split``, as a folder
    ``out`` holding ``background.ply`` and ``agent-<track id>.ply`` per agent present (made whole or not at all;
    ``overwrite`` replaces a folder omniscs wrote); returns the files written."""
    nodes = frame_gaussians(graph, frame)
    out = Path(out)
    if not split:
        return [write_gaussian_ply(concat_params([p for p in nodes.values() if len(p)]), out)]
    names = {key: "background.ply" if key == BACKGROUND else f"agent-{key.split('.', 1)[1]}.ply" for key in nodes}
    with atomic_directory(out, overwrite=overwrite) as tmp:
        for key, params in nodes.items():
            if len(params):
                write_gaussian_ply(params, tmp / names[key])
    return [out / names[key] for key, params in nodes.items() if len(params)]
