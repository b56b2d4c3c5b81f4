"""What the viewer draws, as plain arrays built from a fitted scene graph or a scene store (no viser here): the splats
of each node in its own frame, where each node stands at a frame, agent boxes, the ego and its camera frustums,
trajectories and LiDAR points; and the selected camera's view with the boxes drawn on it."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from omniscs.errors import OmniscsError
from omniscs.gaussians import activate
from omniscs.geometry import invert_transform
from omniscs.nsg.graph import BACKGROUND, SceneGraph, agent_key
from omniscs.preview import box_pose, draw_box_wireframes
from omniscs.quaternions import rotmats_from_unit_quats
from omniscs.render.sh import colors_from_sh
from omniscs.scene.store import CameraRecord, Scene
from omniscs.taxonomy import CATEGORIES

#: Box and trajectory colour (RGB) per category: vehicles warm, people and two-wheelers cool, static objects grey.
CATEGORY_COLOURS: dict[str, tuple[int, int, int]] = {
    "car": (255, 140, 0), "truck": (230, 60, 40), "bus": (200, 30, 120), "trailer": (170, 90, 40),
    "construction_vehicle": (240, 200, 0), "pedestrian": (30, 144, 255), "motorcycle": (0, 200, 200),
    "bicycle": (60, 200, 90), "traffic_cone": (255, 90, 200), "barrier": (150, 150, 150), "debris": (110, 110, 110),
}
assert set(CATEGORY_COLOURS) == set(CATEGORIES), "every taxonomy category needs a viewer colour"
#: Colour of a category outside the taxonomy (a reader's raw label) and of the ego's path and frustums.
OTHER_COLOUR = (200, 200, 200)
EGO_COLOUR = (20, 20, 20)


def category_colour(category: str) -> tuple[int, int, int]:
    return CATEGORY_COLOURS.get(category, OTHER_COLOUR)


@dataclass(frozen=True)
class ViewerConfig:
    """How much the viewer sends to the browser and how it plays."""

    splat_budget: int = 200_000
    """Most Gaussians drawn as splats; beyond it the most opaque are kept (the faint ones add least to the picture),
    counted over all nodes together. Software WebGL (no GPU) redraws 500k splats in seconds (``omniscs bench
    view``)."""
    lidar_budget: int = 60_000
    """Most LiDAR points drawn per frame for a scene store; beyond it every k-th point is kept."""
    play_fps: float = 10.0
    """Frames per second of the play button (the logs are 10 Hz)."""
    frustum_scale_m: float = 1.0
    """Drawn depth of a camera frustum (metres)."""

    def __post_init__(self) -> None:
        for name in ("splat_budget", "lidar_budget"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise OmniscsError(f"{name} must be a positive whole number; got {value!r}")
        for name in ("play_fps", "frustum_scale_m"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise OmniscsError(f"{name} must be a positive number; got {value!r}")


# ----------------------------------------------------------------------------- splats
@dataclass(frozen=True)
class Splats:
    """Gaussians as viser's splat node takes them (``scene.add_gaussian_splats``), in the frame of their node."""

    centers: np.ndarray      # [N, 3] float32 metres
    covariances: np.ndarray  # [N, 3, 3] float32 metres²
    rgbs: np.ndarray         # [N, 3] float32 in [0, 1]: the view-independent (band-0) colour
    opacities: np.ndarray    # [N, 1] float32 in (0, 1)

    def __len__(self) -> int:
        return self.centers.shape[0]


def splat_layers(graph: SceneGraph, budget: int) -> dict[str, Splats]:
    """{node key (``BACKGROUND``, ``agent_key(track)``): its Gaussians as splats in the node's frame}, activated once
    (``gaussians.activate``) and cut to the ``budget`` most opaque over all nodes (ties: the earlier Gaussian).
    Colours are band 0 of the SH: viser's splats are not view-dependent. Agents with relight data show the colours
    their Gaussians hold (unlit), as the PLY export does."""
    nodes = {BACKGROUND: graph.background, **{agent_key(a.track_id): a.gaussians for a in graph.agents}}
    activated = {key: activate(params.detached().to("cpu")) for key, params in nodes.items()}
    opacity = torch.cat([g.opacities for g in activated.values()]).numpy()
    keep = np.ones(len(opacity), dtype=bool)
    if len(opacity) > budget:
        keep[:] = False
        keep[np.argsort(-opacity, kind="stable")[:budget]] = True
    out, start = {}, 0
    for key, g in activated.items():
        mask = torch.from_numpy(keep[start:start + len(g)])
        start += len(g)
        rotation = rotmats_from_unit_quats(g.quats[mask])             # [n, 3, 3]
        scales = g.scales[mask]                                        # [n, 3]
        covariances = rotation @ torch.diag_embed(scales ** 2) @ rotation.transpose(1, 2)
        rgb = colors_from_sh(0, g.sh[mask], torch.zeros(1, int(mask.sum()), 3))[0].clamp(0.0, 1.0)
        out[key] = Splats(g.means[mask].numpy().astype(np.float32), covariances.numpy().astype(np.float32),
                          rgb.numpy().astype(np.float32), g.opacities[mask].numpy().astype(np.float32)[:, None])
    return out


# ----------------------------------------------------------------------------- one frame
@dataclass(frozen=True)
class NodePlacement:
    """Where a node's splat layer stands at a frame."""

    key: str                     # BACKGROUND or agent_key(track_id)
    world_from_node: np.ndarray  # [4, 4] float64


@dataclass(frozen=True)
class AgentBox:
    """An agent's (or a logged track's) box at a frame."""

    track_id: int               # negative: the ego's own box (a closed-loop run's replay)
    category: str
    world_from_box: np.ndarray  # [4, 4] float64: box centre, x along the heading
    size: np.ndarray            # [3] float64 (length, width, height) metres
    colour: tuple[int, int, int]  # RGB of the category

    @property
    def label(self) -> str:
        return self.category if self.track_id < 0 else f"{self.category} {self.track_id}"  # < 0: the ego's own


@dataclass(frozen=True)
class Frustum:
    """A camera of the ego's rig at a frame (OpenCV axes: x right, y down, z forward, as viser's frustums)."""

    camera: str
    world_from_camera: np.ndarray  # [4, 4] float64
    fov_y: float                   # vertical field of view, radians
    aspect: float                  # width / height


@dataclass(frozen=True)
class FrameState:
    """Everything the 3D view shows at one frame."""

    frame: int
    world_from_ego: np.ndarray           # [4, 4] float64
    nodes: tuple[NodePlacement, ...]     # splat layers shown and their poses (a fitted graph; empty for a store)
    boxes: tuple[AgentBox, ...]          # agents present, by track id
    frustums: tuple[Frustum, ...]        # the rig's cameras
    points: np.ndarray | None = None     # [M, 3] float32 world LiDAR points (a scene store), else None


def frustum(camera: CameraRecord, world_from_ego: np.ndarray) -> Frustum:
    fy = float(camera.K[1, 1])
    fov_y = 2.0 * float(np.arctan2(0.5 * camera.height, fy))
    return Frustum(camera.name, world_from_ego @ camera.ego_from_camera, fov_y, camera.width / camera.height)


def graph_frame(graph: SceneGraph, frame: int, world_from_ego: np.ndarray | None = None) -> FrameState:
    """The graph at ``frame``: the background where it was fitted, each agent present at its pose, its box, and the
    logged rig on the logged ego pose (or on ``world_from_ego[frame]``, [F, 4, 4]: a variant's ego)."""
    f = graph.check_frame(frame)
    ego = graph.world_from_ego[f] if world_from_ego is None else np.asarray(world_from_ego, np.float64)[f]
    nodes = [NodePlacement(BACKGROUND, np.eye(4))]
    boxes = []
    for a in graph.agents:
        if not a.present[f]:
            continue
        nodes.append(NodePlacement(agent_key(a.track_id), a.world_from_agent[f].copy()))
        boxes.append(AgentBox(a.track_id, a.category, a.world_from_agent[f].copy(), np.array(a.size, np.float64),
                              category_colour(a.category)))
    return FrameState(f, ego.copy(), tuple(nodes), tuple(boxes), tuple(frustum(c, ego) for c in graph.cameras))


def store_boxes(scene: Scene, frame: int) -> tuple[AgentBox, ...]:
    """The store's logged boxes at ``frame``, by track id."""
    return tuple(AgentBox(int(row.track_id), row.category, box_pose(row),
                          np.array([row.length, row.width, row.height], np.float64), category_colour(row.category))
                 for row in scene.boxes_at(frame).sort_values("track_id").itertuples())


def store_frame(scene: Scene, frame: int, lidar_budget: int) -> FrameState:
    """The store at ``frame``: its logged boxes, the rig on the ego pose and the frame's LiDAR sweep in the world
    frame (every k-th point when the sweep holds more than ``lidar_budget``)."""
    f = scene.check_frame(frame)
    ego = scene.world_from_ego(f)
    boxes = store_boxes(scene, f)
    points = None
    if scene.has_lidar:
        sweep = scene.lidar(f)[:, :3].astype(np.float64)       # [N, 3] ego frame
        stride = max(1, -(-len(sweep) // lidar_budget))
        sweep = sweep[::stride]
        points = (sweep @ ego[:3, :3].T + ego[:3, 3]).astype(np.float32)
    return FrameState(f, ego, (), boxes, tuple(frustum(scene.camera(c), ego) for c in scene.camera_names), points)


# ----------------------------------------------------------------------------- trajectories
@dataclass(frozen=True)
class Trajectory:
    """A path over the log: an agent's box centres, or the ego's origin (``track_id`` None)."""

    track_id: int | None
    category: str          # "ego" for the ego
    positions: np.ndarray  # [M, 3] float64 world, at the frames where the track is present
    frames: np.ndarray     # [M] int64
    tint: tuple[int, int, int] | None = None  # a colour of its own (e.g. a variant's original paths), else by kind

    @property
    def colour(self) -> tuple[int, int, int]:
        if self.tint is not None:
            return self.tint
        return EGO_COLOUR if self.track_id is None else category_colour(self.category)


def graph_trajectories(graph: SceneGraph, world_from_ego: np.ndarray | None = None) -> tuple[Trajectory, ...]:
    """The ego's path (logged, or ``world_from_ego`` [F, 4, 4]), then each agent node's path (as edited, for an
    edited graph)."""
    frames = np.arange(graph.n_frames)
    ego = graph.world_from_ego if world_from_ego is None else np.asarray(world_from_ego, np.float64)
    out = [Trajectory(None, "ego", ego[:, :3, 3].copy(), frames)]
    for a in graph.agents:
        out.append(Trajectory(a.track_id, a.category, a.world_from_agent[a.present, :3, 3].copy(), frames[a.present]))
    return tuple(out)


def store_trajectories(scene: Scene) -> tuple[Trajectory, ...]:
    """The ego's logged path, then each logged track's box centres."""
    out = [Trajectory(None, "ego", scene.world_from_ego_all[:, :3, 3].copy(), np.arange(scene.n_frames))]
    for tid, rows in scene.boxes.sort_values(["track_id", "frame_idx"]).groupby("track_id", sort=True):
        out.append(Trajectory(int(tid), str(rows["category"].iloc[0]), rows[["cx", "cy", "cz"]].to_numpy(np.float64),
                              rows["frame_idx"].to_numpy(np.int64)))
    return tuple(out)


# ----------------------------------------------------------------------------- the road map
#: Colours of lane centrelines and of the drivable area's outline.
LANE_COLOUR = (250, 250, 250)
DRIVABLE_COLOUR = (90, 90, 90)


def road_lines(road_map, ground_z: float,
               ) -> tuple[np.ndarray, np.ndarray]:  # segments [S, 2, 3] world, uint8 colours [S, 2, 3]
    """A road map (``omniscs.roadmap.RoadMap``, 2D) as line segments at height ``ground_z``: every lane centreline
    and the outline of every drivable polygon (their union is the drivable area)."""
    segments, colours = [], []
    for lines, closed, colour in ((road_map.lane_centrelines, False, LANE_COLOUR),
                                  (road_map.drivable_polygons, True, DRIVABLE_COLOUR)):
        for line in lines:
            xy = np.asarray(line, dtype=np.float64).reshape(-1, 2)
            if closed and len(xy) > 2:
                xy = np.concatenate([xy, xy[:1]])
            if len(xy) < 2:
                continue
            xyz = np.concatenate([xy, np.full((len(xy), 1), float(ground_z))], 1)
            segments.append(np.stack([xyz[:-1], xyz[1:]], 1))
            colours.append(np.tile(np.array(colour, np.uint8), (len(xy) - 1, 2, 1)))
    if not segments:
        return np.zeros((0, 2, 3)), np.zeros((0, 2, 3), np.uint8)
    return np.concatenate(segments), np.concatenate(colours)


def ray_ground_point(origin, direction, ground_z: float) -> np.ndarray | None:  # [3], [3] world -> [3] or None
    """Where the ray ``origin + s direction`` (s > 0) meets the plane z = ``ground_z``; None when it never does
    (it points level or up, away from the plane)."""
    o, d = np.asarray(origin, dtype=np.float64), np.asarray(direction, dtype=np.float64)
    if abs(d[2]) < 1e-9:
        return None
    s = (float(ground_z) - o[2]) / d[2]
    return o + s * d if s > 0 else None


def ground_height(world_from_ego: np.ndarray) -> float:  # [F, 4, 4] -> metres
    """Height of the road under the log: the ego frame's origin lies on the ground (DESIGN.md), so its median."""
    return float(np.median(world_from_ego[:, 2, 3]))


# ----------------------------------------------------------------------------- the camera view
def rendered_image(graph: SceneGraph, camera: str, frame: int,
                   world_from_ego: np.ndarray | None = None) -> np.ndarray:  # -> uint8 [H, W, 3] RGB
    """The logged camera at ``frame`` through the scene graph's renderer, as ``omniscs render`` writes it (on the
    ego pose ``world_from_ego[frame]`` when given, [F, 4, 4])."""
    ego = None if world_from_ego is None else np.asarray(world_from_ego, np.float64)[frame]
    result = graph.render(graph.view(camera, frame, ego))
    return (result.rgb.detach().cpu().clamp(0, 1).numpy() * 255).round().astype(np.uint8)


#: Box colours of the selected agent and of a variant's adversary.
SELECTED_COLOUR = (255, 255, 255)
ADVERSARY_COLOUR = (255, 0, 0)


def box_colour(box: AgentBox, selected: int | None = None, adversary: int | None = None) -> tuple[int, int, int]:
    if box.track_id == selected:
        return SELECTED_COLOUR
    return ADVERSARY_COLOUR if box.track_id == adversary else box.colour


def with_boxes(image: np.ndarray,     # uint8 [H, W, 3]
               camera: CameraRecord, world_from_ego: np.ndarray,  # [4, 4]
               boxes: tuple[AgentBox, ...], highlight: int | None = None, adversary: int | None = None,
               ) -> np.ndarray:
    """``image`` with ``boxes`` drawn as projected wireframes in their category colours (track ``highlight`` in
    white, a variant's ``adversary`` in red)."""
    cam_from_world = invert_transform(world_from_ego @ camera.ego_from_camera)
    drawn = [(b.world_from_box, b.size, b.label, box_colour(b, highlight, adversary)) for b in boxes]
    return draw_box_wireframes(image, camera.K, cam_from_world, drawn)


def graph_camera_image(graph: SceneGraph, camera: str, frame: int, boxes: bool = True,
                       highlight: int | None = None, scene: Scene | None = None,
                       world_from_ego: np.ndarray | None = None,  # [F, 4, 4] a variant's ego, else the logged one
                       adversary: int | None = None) -> np.ndarray:  # -> uint8 [H, W (x2 with scene), 3]
    """The camera view of a fitted graph: rendered, with the agents' boxes drawn when ``boxes``; with the ``scene``
    it was fitted to, the logged image (its logged boxes drawn) to the left of the rendered one."""
    image = rendered_image(graph, camera, frame, world_from_ego)
    if boxes:
        state = graph_frame(graph, frame, world_from_ego)
        image = with_boxes(image, graph.camera(camera), state.world_from_ego, state.boxes, highlight, adversary)
    if scene is None or camera not in scene.camera_names:
        return image
    logged = store_camera_image(scene, camera, frame, boxes)
    if logged.shape != image.shape:  # the rig was rendered at another size than it was logged
        import cv2

        logged = cv2.resize(logged, (image.shape[1], image.shape[0]), interpolation=cv2.INTER_AREA)
    return np.concatenate([logged, image], axis=1)


def store_camera_image(scene: Scene, camera: str, frame: int, boxes: bool = True) -> np.ndarray:  # uint8 [H, W, 3]
    """The camera view of a scene store: the logged image, with the logged boxes drawn when ``boxes``."""
    image = scene.image(camera, frame)
    if not boxes:
        return image
    return with_boxes(image, scene.camera(camera), scene.world_from_ego(frame), store_boxes(scene, frame))
