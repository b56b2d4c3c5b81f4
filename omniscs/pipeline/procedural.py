"""The procedural world as a source of traffic for the behaviour model, never rendered: ``syn:`` logs, training
logs and benchmark scenes. Model code never imports the world; this wiring hands it neutral arrays and a RoadMap."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from omniscs.edits import Insert, ReplaceModel, SetTrajectory, parse_edits
from omniscs.errors import OmniscsError
from omniscs.geometry import yaw_from_matrix
from omniscs.scene import load_scene
from omniscs.scene.ingest import Source, StoreSource, check_synthetic
from omniscs.scene.synthetic import SyntheticSource
from omniscs.scs.behavior.maps import MapConfig
from omniscs.scs.behavior.tracks import EgoBox, TrafficScene, traffic_from_log, traffic_from_scene
from omniscs.world import WorldRenderer, apply_edits, generate_world, road_map_for
from omniscs.world.assets import asset_split

#: Sensor rig of procedural logs made only for their traffic: nothing is rendered, so the smallest one.
TRAFFIC_ONLY_RIG = dict(n_cameras=1, width=64, height=36)


def traffic_from_world(world, scene_id: str | None = None, ego_box: EgoBox = EgoBox(),
                       map_config: MapConfig = MapConfig()) -> TrafficScene:
    """The traffic of a procedural ``omniscs.world.World`` (no rendering), with its layout's road map."""
    agents = world.agents
    n, s = len(agents), world.n_frames
    return traffic_from_log(
        scene_id or f"world-{world.template}-s{world.seed}", world.timestamps_us(), world.ego_poses,
        track_ids=np.array([a.track_id for a in agents], dtype=np.int64),
        categories=tuple(a.category for a in agents),
        sizes=np.array([a.size for a in agents], dtype=np.float64).reshape(-1, 3),
        world_from_agent=np.array([a.poses for a in agents], dtype=np.float64).reshape(n, s, 4, 4),
        present=np.array([a.present for a in agents], dtype=bool).reshape(n, s),
        dt=world.frame_period_us / 1e6, road_map=road_map_for(world), ego_box=ego_box, map_config=map_config)


def procedural_traffic(template: str, seed: int, n_frames: int, scene_id: str | None = None) -> TrafficScene:
    """The traffic of the procedural log (template, seed) with ``n_frames`` frames; raises OmniscsError for a seed
    that cannot be built. This is the ``ProceduralLogs`` source that ``train_model`` takes."""
    world = generate_world(template, int(seed), n_frames=int(n_frames), **TRAFFIC_ONLY_RIG)
    return traffic_from_world(world, scene_id=scene_id)


def procedural_scenes(templates, first_seed: int, n: int) -> list[tuple[str, int]]:
    """(template, seed) of ``n`` procedural logs from ``first_seed`` on, the templates in turn: how the planning
    protocol lays out its scenes, and so how a planner's training record (templates, seed range) names its logs."""
    return [(templates[k % len(templates)], int(first_seed) + k) for k in range(int(n))]


def procedural_scene_id(template: str, seed: int) -> str:
    """The scene id the planning protocol gives the procedural log (template, seed)."""
    return f"syn-{template}-s{seed}"


def traffic_for_source(source: Source, dt: float = 0.1) -> TrafficScene:
    """The traffic of a parsed source (``omniscs.scene.parse_source``): a ``syn:`` log is generated, not rendered
    (scene id ``syn-TEMPLATE-sSEED``; lighting does not change traffic); a scene store is read on a ``dt`` grid."""
    if isinstance(source, SyntheticSource):
        check_synthetic(source)
        return procedural_traffic(source.template, source.seed, source.n_frames,
                                  scene_id=f"syn-{source.template}-s{source.seed}")
    if isinstance(source, StoreSource):
        return traffic_from_scene(load_scene(Path(source.path)), dt=dt)
    raise OmniscsError(f"{source.format}:{source.dataroot} is a dataset, not a scene store; ingest it first "
                       "(`omniscs ingest`) and pass the scene store it writes")



def variant_world(world, vf):
    """The procedural ``world`` as a variant made it: every agent node the variant moved where it was placed in the
    rendered frames (logged poses elsewhere), the ego where it drove. Same frames as the world."""
    def xyz_yaw(T: np.ndarray) -> tuple:
        return float(T[0, 3]), float(T[1, 3]), float(T[2, 3]), float(yaw_from_matrix(T[:3, :3]))

    n = world.n_frames
    moved: dict[int, list] = {}
    for t, placed in enumerate(vf.node_poses):
        for tid, T in placed.items():
            moved.setdefault(tid, [None] * n)[int(vf.scene_frames[t])] = xyz_yaw(T)
    by_id = {a.track_id: a for a in world.agents}
    edits = []
    for tid, waypoints in moved.items():  # frames the variant does not render keep the logged pose
        agent = by_id[tid]
        edits.append(SetTrajectory(int(tid), tuple(
            w if w is not None else (xyz_yaw(agent.poses[f]) if agent.present[f] else None)
            for f, w in enumerate(waypoints))))
    edited = apply_edits(world, edits)
    ego = np.array(edited.ego_poses, dtype=np.float64, copy=True)
    ego[np.asarray(vf.scene_frames, dtype=np.int64)] = vf.world_from_ego
    return edited.replace(ego_poses=ego)


def variant_renderer(scene):
    """For a procedural scene, ``vf -> WorldRenderer`` of ``variant_world`` for a rendered variant's frames, keeping
    the one for the variant asked for last (its frames' ray-casting scenes are built once for every sensor that
    shares it); None for recorded logs."""
    world = scene.world
    if world is None:
        return None
    held: list = []

    def renderer(vf) -> WorldRenderer:
        if not held or held[0] is not vf:
            held[:] = [vf, WorldRenderer(variant_world(world, vf))]
        return held[1]

    return renderer


def world_reference(scene, renderer=None):
    """For a procedural scene, the exact image of any rendered variant frame (``annotate.variant.Reference``):
    ``variant_world`` ray-cast (through ``renderer``, a ``variant_renderer`` to share); None for recorded logs
    (their fidelity is the viewpoint proxy only)."""
    renderer = renderer or variant_renderer(scene)
    if renderer is None:
        return None

    def reference(vf, camera: str, t: int):
        r = renderer(vf).render_camera(int(vf.scene_frames[t]), camera)
        return r.rgb, r.instance

    return reference


def world_lidar(scene, renderer=None):
    """For a procedural scene, the exact LiDAR sweep of any rendered variant frame (``annotate.variant.Sweep``):
    ``variant_world`` ray-cast with the world's own spinning sensor (``omniscs.world.model.LidarSpec``; through
    ``renderer``, a ``variant_renderer`` to share), points in the ego frame; None for recorded logs (their
    variants' sweeps come from the scene graph's depth)."""
    renderer = renderer or variant_renderer(scene)
    if renderer is None:
        return None
    return lambda vf, t: renderer(vf).lidar_scan(int(vf.scene_frames[t]))


def world_description(scene):
    """For a procedural scene, ``vf -> world.json`` of a rendered variant (``variant_world`` cut to the rendered
    frames), so a variant's store describes its own roads and traffic like any synthetic store; None otherwise."""
    world = scene.world
    if world is None:
        return None

    def describe(vf) -> str:
        frames = np.asarray(vf.scene_frames, dtype=np.int64)
        edited = variant_world(world, vf)
        agents = tuple(a.__class__(track_id=a.track_id, category=a.category, asset_id=a.asset_id, size=a.size,
                                   poses=a.poses[frames], present=a.present[frames]) for a in edited.agents)
        period = int(np.median(np.diff(vf.timestamps_us))) if len(frames) > 1 else edited.frame_period_us
        return edited.replace(n_frames=len(frames), ego_poses=edited.ego_poses[frames], agents=agents,
                              frame_period_us=period).to_json()

    return describe


def appearance_world(world, variant: dict, asset_of):
    """The procedural ``world`` with an appearance variant's edits, each object model replaced by the library asset it
    was built from (``asset_of(model id) -> asset id`` or None); None when an object has no asset of the library."""
    edits = []
    for e in parse_edits(variant["edits"]):
        if isinstance(e, (Insert, ReplaceModel)):
            asset = asset_of(e.asset_id)
            if asset is None:
                return None
            e = dataclasses.replace(e, asset_id=asset)
        edits.append(e)
    return apply_edits(world, edits)


def appearance_renderer(scene, asset_of):
    """For a procedural scene, ``variant -> WorldRenderer`` of ``appearance_world`` (None for a variant whose object
    has no asset of the library), keeping the one for the variant asked for last so that its exact images and its
    LiDAR share it; None for recorded logs."""
    world = scene.world
    if world is None:
        return None
    held: list = []

    def renderer(variant: dict) -> WorldRenderer | None:
        if not held or held[0] is not variant:
            edited = appearance_world(world, variant, asset_of)
            held[:] = [variant, None if edited is None else WorldRenderer(edited)]
        return held[1]

    return renderer


def appearance_reference(scene, asset_of, renderer=None):
    """For a procedural scene, ``variant -> Reference`` of appearance variants: ``appearance_world`` ray-cast
    (through ``renderer``, an ``appearance_renderer`` to share); None for recorded logs, and a variant whose object
    has no asset of the library gets no reference."""
    renderer = renderer or appearance_renderer(scene, asset_of)
    if renderer is None:
        return None

    def for_variant(variant: dict):
        world = renderer(variant)
        if world is None:
            return None

        def reference(vf, name: str, t: int):
            r = world.render_camera(int(vf.scene_frames[t]), name)
            return r.rgb, r.instance
        return reference

    return for_variant


def appearance_lidar(scene, asset_of, renderer=None):
    """For a procedural scene, ``variant -> Sweep`` of appearance variants: ``appearance_world`` ray-cast with the
    world's own sensor (through ``renderer``, an ``appearance_renderer`` to share); None for recorded logs, and a
    variant whose object has no asset of the library gets none."""
    renderer = renderer or appearance_renderer(scene, asset_of)
    if renderer is None:
        return None

    def for_variant(variant: dict):
        world = renderer(variant)
        return None if world is None else (lambda vf, t: world.lidar_scan(int(vf.scene_frames[t])))

    return for_variant


def pool_asset_of(pool):
    """``model id -> asset id`` of the library asset a pool model was built from (provenance mesh), else None."""
    table = pool.table() if pool is not None else None

    def asset_of(model_id: str):
        if table is None or table.empty:
            return None
        row = table[table.model_id == model_id]
        if row.empty or row.iloc[0].provenance != "mesh":
            return None
        source = str(row.iloc[0].source)
        try:
            asset_split(source)
        except Exception:  # not an id of the library (a user's mesh file)
            return None
        return source

    return asset_of
