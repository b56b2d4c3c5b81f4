"""A fitted scene graph of a small procedural log and hand-made variants of it, for the render + annotate tests
(module-scoped: the fit takes about 5 s)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from nsg_fixtures import nsg_world, tiny_fit_config, write_nsg_scene
from omniscs.geometry import yaw_from_matrix

#: Ego box centre ahead of the ego origin (the synthetic ego's, as the behaviour model uses it).
AHEAD_M = 1.3


def fitted_scene(out: Path, agents=None, n_frames: int = 10, n_cameras: int = 2, iterations: int = 200):
    """(scene, graph) of ``nsg_world`` fitted at thumbnail size, every track an agent node."""
    from omniscs.nsg.checkpoint import load_graph
    from omniscs.nsg.train import fit_scene
    from omniscs.plan import make_plan
    from omniscs.scene import load_scene

    kwargs = {} if agents is None else {"agents": agents}
    world = nsg_world(n_frames=n_frames, n_cameras=n_cameras, width=96, height=54, **kwargs)
    scene = load_scene(write_nsg_scene(out / "scene", world))
    config = tiny_fit_config(iterations)
    plan = make_plan(scene, config=config.plan, behavior_variants=1)
    fit_scene(scene, config, plan, checkpoint_dir=out / "graph", overwrite=True)
    return scene, load_graph(out / "graph", scene)


def logged_variant(scene, shift: dict[int, float] | None = None, adversary: int = 2, ego_lateral=None) -> dict:
    """A variants.json entry replaying the log, with track ``t`` drifting ``shift[t]`` metres to its right per frame
    and the ego shifted ``ego_lateral(frame)`` metres to its left."""
    shift = shift or {}
    frames = list(range(scene.n_frames))
    agents = {}
    for tid, g in scene.boxes.groupby("track_id"):
        g = g.set_index("frame_idx")
        agents[str(tid)] = [[float(g.loc[f].cx), float(g.loc[f].cy) - shift.get(int(tid), 0.0) * f, float(g.loc[f].yaw)]
                            if f in g.index else None for f in frames]
    ego = scene.world_from_ego_all
    rows = []
    for f in frames:
        yaw = float(yaw_from_matrix(ego[f, :3, :3]))
        lateral = 0.0 if ego_lateral is None else float(ego_lateral(f))
        rows.append([float(ego[f, 0, 3] + AHEAD_M * np.cos(yaw) - lateral * np.sin(yaw)),
                     float(ego[f, 1, 3] + AHEAD_M * np.sin(yaw) + lateral * np.cos(yaw)), yaw])
    return {"variant_id": "v000", "scene_id": scene.scene_id, "source_frames": frames, "ego": rows,
            "agents": agents, "adversary": adversary, "ego_centre_ahead_of_origin_m": AHEAD_M, "now_step": 3,
            "dt": 0.1}
