"""What ``omniscs view`` can open, each as the view state it draws and the edits it takes: a fitted scene-graph
checkpoint (optionally with the store it was fitted to and a model pool), a scene store, a dataset, or a closed-loop
run folder (``omniscs.viewer.runs``)."""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from omniscs.errors import OmniscsError
from omniscs.geometry import yaw_from_matrix
from omniscs.nsg.graph import BACKGROUND
from omniscs.viewer.session import EditSession
from omniscs.viewer.state import (FrameState, Splats, Trajectory, ViewerConfig, graph_camera_image, graph_frame,
                                  graph_trajectories, ground_height, ray_ground_point, road_lines, splat_layers,
                                  store_camera_image, store_frame, store_trajectories)

#: Colour of the log's paths under a variant's (the original trajectories, overlaid).
ORIGINAL_COLOUR = (150, 150, 150)
#: Progress callback: (steps done, steps in all, what is happening).
Progress = Callable[[int, int, str], None]


class GraphTarget:
    """A fitted scene-graph checkpoint: splats, agent boxes, the rig, and edits of its agents."""

    kind = "fitted scene graph"
    editable = True

    def __init__(self, path: Path, graph, config: ViewerConfig, progress: Progress | None = None,
                 scene=None, pool: Path | None = None) -> None:
        from omniscs.nsg.edit import node_model_resolver

        self.path = path
        self.scene = scene  # the store it was fitted to, when given: logged images and the road map
        self.pool = pool    # a model pool whose models can replace agents or be inserted
        resolve = node_model_resolver(graph)
        if pool is not None:
            from omniscs.agents.pool import model_resolver

            resolve = model_resolver(pool, resolve)
        self._resolve = resolve
        self._reserved = () if scene is None else tuple(int(t) for t in scene.boxes.track_id.unique())
        self.session = EditSession(graph, resolve, reserved_ids=self._reserved)
        self.variants: list[dict] = []  # a stage's variants to pick from (open_target's ``variants``)
        self.variant: dict | None = None
        self.ego: np.ndarray | None = None  # [F, 4, 4] the picked variant's ego, else None (the logged one)
        self.config = config
        if progress:
            kept = min(graph.n_gaussians, config.splat_budget)
            progress(1, 2, f"{graph.n_gaussians:,} Gaussians: activating, keeping {kept:,}")
        # moves and removals never change a node's Gaussians: layers are made again only when a model changes
        self.layers: dict[str, Splats] = splat_layers(graph, config.splat_budget)
        self._layer_sources = self._sources(graph)
        self.n_gaussians = graph.n_gaussians
        self.placement = None
        if scene is not None:
            from omniscs.viewer.placement import LivePlacement

            if progress:
                progress(1, 2, "gathering the log's road, ground and boxes for the placement checks")
            self.placement = LivePlacement(scene)
        self.scene_id = graph.scene_id
        self.n_frames = graph.n_frames
        self.camera_names = [c.name for c in graph.cameras]

    @property
    def adversary(self) -> int | None:
        """The picked variant's adversary (drawn red), else None."""
        return None if self.variant is None or self.variant.get("adversary") is None else int(self.variant["adversary"])

    def pick_variant(self, index: int | None) -> None:
        """Show ``variants[index]`` (None: the log): a new session whose edits start with the variant's, the ego on
        its plan; edits made before are dropped."""
        from omniscs.viewer.variants import variant_edits, variant_ego

        variant = None if index is None else self.variants[index]
        prefix = [] if variant is None else variant_edits(self.session.base, variant)
        self.session = EditSession(self.session.base, self._resolve, self._reserved, prefix)
        self.variant = variant
        self.ego = None if variant is None else variant_ego(self.session.base, variant)

    def frame_state(self, frame: int) -> FrameState:
        return graph_frame(self.session.graph, frame, self.ego)

    def trajectories(self) -> tuple[Trajectory, ...]:
        """The paths as edited; with a variant picked, the log's paths too (grey) where the variant changed them."""
        edited = graph_trajectories(self.session.graph, self.ego)
        if self.variant is None:
            return edited
        logged = {t.track_id: t for t in graph_trajectories(self.session.base)}
        originals = tuple(Trajectory(t.track_id, t.category, logged[t.track_id].positions,
                                     logged[t.track_id].frames, tint=ORIGINAL_COLOUR)
                          for t in edited if t.track_id in logged and (
                              len(t.positions) != len(logged[t.track_id].positions)
                              or not np.allclose(t.positions, logged[t.track_id].positions, atol=1e-3)))
        return edited + originals

    def camera_image(self, camera: str, frame: int, boxes: bool, highlight: int | None = None) -> np.ndarray:
        return graph_camera_image(self.session.graph, camera, frame, boxes, highlight, self.scene, self.ego,
                                  self.adversary)

    @staticmethod
    def _sources(graph) -> dict[str, int]:
        return {BACKGROUND: id(graph.background), **{f"agent.{a.track_id}": id(a.gaussians) for a in graph.agents}}

    def set_budget(self, budget: int) -> set[str]:
        """Draw at most ``budget`` Gaussians from now on (the most opaque); returns the keys of the layers made
        again (all of them)."""
        import dataclasses

        self.config = dataclasses.replace(self.config, splat_budget=int(budget))  # checked by ViewerConfig
        self._layer_sources = {}
        return self.changed_layers()

    def changed_layers(self) -> set[str]:
        """After an edit: the splat layers made again because a node's model changed or a node came or went (their
        keys; a removed node's layer is empty)."""
        sources = self._sources(self.session.graph)
        if sources == self._layer_sources:
            return set()
        old = self.layers
        self.layers = splat_layers(self.session.graph, self.config.splat_budget)
        changed = {k for k in set(sources) | set(self._layer_sources)
                   if sources.get(k) != self._layer_sources.get(k)
                   or len(self.layers.get(k, ())) != len(old.get(k, ()))}
        for key in changed - set(self.layers):
            self.layers[key] = Splats(*(np.zeros(shape, np.float32) for shape in ((0, 3), (0, 3, 3), (0, 3), (0, 1))))
        self._layer_sources = sources
        self.n_gaussians = self.session.graph.n_gaussians
        return changed

    def models(self) -> list[tuple[str, str]]:
        """(model id, category) of every model an agent can take: the pool's, then this graph's own agent nodes."""
        out = []
        if self.pool is not None:
            from omniscs.agents.pool import Pool

            table = Pool(self.pool).table()
            out += [(str(r.model_id), str(r.category)) for r in table.itertuples()]
        out += [(f"nsg:{a.track_id}", a.category) for a in self.session.base.agents]
        return out

    def ground_point(self, ray_origin, ray_direction, frame: int) -> tuple[float, float, float] | None:
        """Where a click's ray meets the road (x, y, ground z), or None when it points above the horizon: the
        road's height there from the log (with ``scene``), else the plane under the ego's logged path."""
        z = ground_height(self.session.base.world_from_ego)
        hit = ray_ground_point(ray_origin, ray_direction, z)
        if hit is None:
            return None
        if self.placement is not None:  # refine on the log's ground height under the hit point
            z = float(self.placement.logged.ground_z(hit[None, :2])[0])
            hit = ray_ground_point(ray_origin, ray_direction, z)
        return None if hit is None else (float(hit[0]), float(hit[1]), z)

    def heading_at(self, x: float, y: float, frame: int) -> float:
        """The heading an inserted object takes: the nearest lane's (with ``scene``), else the ego's at ``frame``."""
        if self.placement is not None and self.placement.logged.lane_direction is not None:
            yaw, found = self.placement.logged.lane_direction(np.array([[x, y]]))
            if found[0]:
                return float(yaw[0])
        return float(yaw_from_matrix(self.session.base.world_from_ego[frame][:3, :3]))

    def placement_verdict(self, track_id: int) -> str | None:
        """One line on the placement checks of agent ``track_id`` as edited (None without the scene store)."""
        if self.placement is None:
            return None
        result = self.placement.check(self.session.graph, track_id, self.session.removed)
        if result.ok:
            return f"Placement of agent {track_id}: on the road, clear of every box, seen by a camera."
        return f"Placement of agent {track_id}: " + "; ".join(result.failures) + "."

    def road(self) -> tuple[np.ndarray, np.ndarray] | None:
        if self.scene is None or self.scene.road_map is None:
            return None
        return road_lines(self.scene.road_map, ground_height(self.session.base.world_from_ego))

    def summary(self) -> str:
        n_shown = sum(len(s) for s in self.layers.values())
        return (f"**{self.scene_id}** ({self.kind}): {self.n_frames} frames, {len(self.session.base.agents)} agent "
                f"nodes, {n_shown:,} of {self.n_gaussians:,} Gaussians drawn (the most opaque)")


class StoreTarget:
    """A scene store without a fit: LiDAR points, logged boxes, the rig and the logged camera images."""

    kind = "scene store"
    editable = False

    def __init__(self, path: Path, scene, config: ViewerConfig) -> None:
        self.path = path
        self.scene = scene
        self.config = config
        self.layers: dict[str, Splats] = {}
        self.scene_id = scene.scene_id
        self.n_frames = scene.n_frames
        self.camera_names = list(scene.camera_names)

    def frame_state(self, frame: int) -> FrameState:
        return store_frame(self.scene, frame, self.config.lidar_budget)

    def trajectories(self) -> tuple[Trajectory, ...]:
        return store_trajectories(self.scene)

    def camera_image(self, camera: str, frame: int, boxes: bool, highlight: int | None = None) -> np.ndarray:
        return store_camera_image(self.scene, camera, frame, boxes)

    def road(self) -> tuple[np.ndarray, np.ndarray] | None:
        if self.scene.road_map is None:
            return None
        return road_lines(self.scene.road_map, ground_height(self.scene.world_from_ego_all))

    def summary(self) -> str:
        lidar = "LiDAR points" if self.scene.has_lidar else "no LiDAR"
        return (f"**{self.scene_id}** ({self.kind}, no fit): {self.n_frames} frames, "
                f"{self.scene.boxes.track_id.nunique()} tracks, {lidar}")


class DatasetTarget(StoreTarget):
    """A dataset (``omniscs dataset build``): its variant stores, one at a time (``pick``), each shown as a scene
    store: the rendered images with their 3D annotation boxes, the LiDAR, the rig."""

    kind = "dataset"

    def __init__(self, path: Path, card: dict, config: ViewerConfig) -> None:
        from omniscs.annotate.dataset import SCENES
        from omniscs.scene.store import load_scene

        self.card = card
        rows = card.get("variants") if isinstance(card, dict) else None
        self.samples = [r for r in (rows if isinstance(rows, list) else [])
                        if isinstance(r, dict) and isinstance(r.get("store_id"), str)
                        and (path / SCENES / r["store_id"]).is_dir()]
        if not self.samples:
            raise OmniscsError(f"dataset {path} lists no variant store under {SCENES}/; build it again "
                               "(omniscs dataset build)")
        self._stores = [path / SCENES / r["store_id"] for r in self.samples]
        self._load = load_scene
        super().__init__(path, load_scene(self._stores[0]), config)
        self.sample = 0
        self.labels = dataset_labels(path)

    def pick(self, index: int) -> None:
        """Show the dataset's ``index``-th variant store."""
        self.scene = self._load(self._stores[index])
        self.sample = index
        self.scene_id = self.scene.scene_id
        self.n_frames = self.scene.n_frames
        self.camera_names = list(self.scene.camera_names)

    def camera_image(self, camera: str, frame: int, boxes: bool, highlight: int | None = None) -> np.ndarray:
        """The variant store's image with its 3D boxes and, when the dataset lists them, its annotations' 2D boxes
        (tight, from the instance mask; else the projected box) labelled ``track vN`` (nuScenes visibility level
        N), the adversary's in red."""
        image = store_camera_image(self.scene, camera, frame, boxes)
        rows = self.labels.get((self.samples[self.sample]["store_id"], int(frame), camera), [])
        return with_labels(image, rows) if boxes and rows else image

    def frame_summary(self, frame: int) -> str:
        """The picked store's annotations at ``frame``, per camera, by visibility level, as one Markdown line."""
        store = self.samples[self.sample]["store_id"]
        parts = []
        for camera in self.camera_names:
            rows = self.labels.get((store, int(frame), camera), [])
            if rows:
                levels = [sum(int(r.get("visibility_level", 0)) == v for r in rows) for v in (1, 2, 3, 4)]
                parts.append(f"{camera} {len(rows)} (v1-v4: {'/'.join(map(str, levels))})")
        return f"Frame {frame} annotations: " + ("; ".join(parts) if parts else "none listed")

    def sample_summary(self) -> str:
        """The picked variant's row of the dataset card, as one Markdown line."""
        r = self.samples[self.sample]
        psnr = r.get("fidelity_psnr")
        return (f"**{r['store_id']}** ({r.get('level', 'behaviour')} variant {r.get('variant_id')} of "
                f"{r.get('scene_id')}): {r.get('n_frames')} frames, {r.get('n_images')} images, "
                f"{r.get('n_annotations')} annotations; gates {'passed' if r.get('passed_gates') else 'FAILED'}"
                + ("" if psnr is None else f"; fidelity {float(psnr):.1f} dB PSNR"))

    def summary(self) -> str:
        counts = self.card.get("counts", {})
        return (f"**{self.card.get('dataset_id', self.path.name)}** ({self.kind}): {len(self.samples)} variant "
                f"stores, {counts.get('images', '?')} images, {counts.get('annotations', '?')} annotations")


#: Largest rows.json a dataset target reads (its every annotation; about 0.5 MB per variant of 20 frames x 3 cameras).
MAX_ROWS_BYTES = 2**30


def dataset_labels(path: Path) -> dict[tuple[str, int, str], list[dict]]:
    """A dataset's annotation rows (its ``rows.json``) by (store id, frame, camera); empty when it has none."""
    from omniscs.annotate.scene import ROWS_JSON
    from omniscs.untrusted import read_json

    if not (path / ROWS_JSON).is_file():
        return {}
    rows = read_json(path / ROWS_JSON, "build the dataset again (omniscs dataset build)", expect=dict,
                     max_bytes=MAX_ROWS_BYTES, what="dataset rows")
    out: dict[tuple[str, int, str], list[dict]] = {}
    for a in rows.get("annotations") or []:
        try:
            key = (str(a["store_id"]), int(a["frame_idx"]), str(a["camera"]))
        except (KeyError, TypeError, ValueError):
            raise OmniscsError(f"{path / ROWS_JSON}: an annotation lacks store_id, frame_idx or camera; build the "
                               "dataset again (omniscs dataset build)") from None
        out.setdefault(key, []).append(a)
    return out


def with_labels(image: np.ndarray, rows: list[dict]) -> np.ndarray:  # uint8 [H, W, 3] -> a copy, boxes drawn
    """``image`` with each annotation's 2D box (tight when it has one, else the projected one) and ``track vN``."""
    import cv2

    from omniscs.annotate.dataset import ADVERSARY_LABEL_COLOUR, LABEL_COLOUR

    out = np.ascontiguousarray(image).copy()
    for a in rows:
        tight = all(a.get(f"tight_{k}") is not None for k in ("x1", "y1", "x2", "y2"))
        x1, y1, x2, y2 = (float(a[f"tight_{k}" if tight else k]) for k in ("x1", "y1", "x2", "y2"))
        if not all(np.isfinite([x1, y1, x2, y2])):
            continue
        colour = ADVERSARY_LABEL_COLOUR if a.get("is_adversary") else LABEL_COLOUR
        p1, p2 = (int(round(x1)), int(round(y1))), (int(round(x2)) - 1, int(round(y2)) - 1)
        cv2.rectangle(out, p1, p2, colour, 1)
        cv2.putText(out, f"{a.get('track_id')} v{a.get('visibility_level', '?')}", (p1[0] + 2, max(p1[1] - 3, 9)),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.35, colour, 1, cv2.LINE_AA)
    return out


#: Workspace folders that hold a scene's fitted graphs (the fit, and the stages that add to it).
GRAPH_FOLDERS = ("fit", "agents", "background")


def variants_context(folder: Path) -> tuple[Path, Path | None, Path | None]:
    """For a variants stage folder of a workspace (``variants/<scene id>/<stage>-<key>/``): the scene's fitted graph
    it was drawn on (the newest graph of the scene's fit, agents or background folders written before the variants;
    the newest otherwise), the scene's store when the workspace has it, and the pool its appearance variants name
    when that folder exists."""
    from omniscs.nsg.checkpoint import GRAPH_JSON
    from omniscs.pipeline import layout
    from omniscs.viewer.variants import VARIANTS_JSON, read_variants

    listed = read_variants(folder)
    scenes = sorted({str(v.get("scene_id")) for v in listed if v.get("scene_id")})
    if len(scenes) != 1:
        raise OmniscsError(f"{folder / VARIANTS_JSON} names {len(scenes)} scenes; a stage's variants belong to one")
    workspace = folder.resolve().parents[2]
    graphs = [g.parent for stage in GRAPH_FOLDERS
              for g in (workspace / layout.FOLDERS[stage] / scenes[0]).glob(f"*/{GRAPH_JSON}")]
    if not graphs:
        raise OmniscsError(f"no fitted scene graph of {scenes[0]} in the workspace {workspace}; open its checkpoint "
                           f"with --variants {folder}")
    drawn = (folder / VARIANTS_JSON).stat().st_mtime
    before = [g for g in graphs if (g / GRAPH_JSON).stat().st_mtime <= drawn] or graphs
    graph = max(before, key=lambda g: (g / GRAPH_JSON).stat().st_mtime)
    store = workspace / layout.FOLDERS["ingest"] / scenes[0]
    pools = sorted({str(v["pool"]) for v in listed if isinstance(v.get("pool"), str) and Path(v["pool"]).is_dir()})
    return graph, store if store.is_dir() else None, Path(pools[0]) if pools else None


def open_target(path: str | Path, config: ViewerConfig | None = None, progress: Progress | None = None,
                scene: str | Path | None = None, pool: str | Path | None = None,
                variants: str | Path | None = None) -> GraphTarget | StoreTarget:
    """What ``path`` holds, opened for viewing: a scene-graph checkpoint (``omniscs fit --out``), optionally with the
    ``scene`` store it was fitted to (logged images beside rendered ones, its road map) and a model ``pool``
    (models to replace agents with or insert) and a stage's ``variants`` (a variants.json, or its folder) to pick
    from, or a scene store
    (``omniscs ingest``, ``omniscs world make``), a dataset (``omniscs dataset build``) or a closed-loop run folder
    (``omniscs closedloop run --out``: a folder with run.json), or a variants stage folder of a workspace (opened on
    the scene's graph, store and pool found there: ``variants_context``); anything else is one OmniscsError."""
    from omniscs.nsg.checkpoint import GRAPH_JSON, check_same_scene, load_graph
    from omniscs.scene.store import MANIFEST, load_scene

    config = config or ViewerConfig()
    path = Path(path)
    if not path.exists():
        raise OmniscsError(f"{path} does not exist; give a scene-graph checkpoint folder (omniscs fit --out), a "
                           "scene store (omniscs ingest, omniscs world make), a dataset or a closed-loop run folder")
    from omniscs.viewer.variants import VARIANTS_JSON

    if path.is_dir() and (path / VARIANTS_JSON).is_file() and not (path / GRAPH_JSON).is_file():
        if variants is not None:
            raise OmniscsError(f"{path} is a variants folder; --variants goes with a scene-graph checkpoint")
        graph_path, found_scene, found_pool = variants_context(path)
        return open_target(graph_path, config, progress, scene if scene is not None else found_scene,
                           pool if pool is not None else found_pool, path)
    if path.is_dir() and (path / GRAPH_JSON).is_file():
        if progress:
            progress(0, 2, f"reading the scene graph {path}")
        graph = load_graph(path)
        store = None
        if scene is not None:
            store = load_scene(scene)
            check_same_scene(graph, store, path)
        if pool is not None and not Path(pool).is_dir():
            raise OmniscsError(f"--pool {pool} is not a folder; give a model pool (omniscs pool build)")
        target = GraphTarget(path, graph, config, progress, store, None if pool is None else Path(pool))
        if variants is not None:
            from omniscs.viewer.variants import read_variants

            target.variants = read_variants(variants)
            others = sorted({str(v.get("scene_id")) for v in target.variants} - {graph.scene_id, "None"})
            if others:
                raise OmniscsError(f"{variants} holds variants of {others}, not of {graph.scene_id}; give that scene's "
                                   "variants")
        if progress:
            progress(2, 2, "ready")
        return target
    from omniscs.annotate.dataset import CARD_JSON

    if path.is_dir() and (path / CARD_JSON).is_file() and not (path / MANIFEST).is_file():
        if scene is not None or pool is not None or variants is not None:
            raise OmniscsError(f"{path} is a dataset; --scene, --pool and --variants go with a scene-graph "
                               "checkpoint")
        from omniscs.untrusted import read_json

        card = read_json(path / CARD_JSON, "build the dataset again (omniscs dataset build)", what="dataset card")
        return DatasetTarget(path, card, config)
    if path.is_dir() and (path / MANIFEST).is_file():
        if scene is not None or pool is not None or variants is not None:
            raise OmniscsError(f"{path} is a scene store; --scene, --pool and --variants go with a scene-graph "
                               "checkpoint (edits need a fit)")
        if progress:
            progress(0, 1, f"opening the scene store {path}")
        target = StoreTarget(path, load_scene(path), config)
        if progress:
            progress(1, 1, "ready")
        return target
    from omniscs.closedloop.run import RUN_JSON
    from omniscs.viewer.runs import ClosedLoopRunTarget, is_run_folder

    if is_run_folder(path):
        if scene is not None or pool is not None or variants is not None:
            raise OmniscsError(f"{path} is a closed-loop run; --scene, --pool and --variants go with a scene-graph "
                               "checkpoint")
        return ClosedLoopRunTarget(path, config)
    raise OmniscsError(f"{path} is neither a scene-graph checkpoint (a folder with {GRAPH_JSON}: omniscs fit --out), "
                       f"a scene store (a folder with {MANIFEST}), a dataset (a folder with {CARD_JSON}) nor a "
                       f"closed-loop run (a folder with {RUN_JSON}: omniscs closedloop run --out); omniscs view "
                       "opens those")
