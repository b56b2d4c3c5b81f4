"""The viewer wired to a viser server: the 3D scene, the panel and its handlers. The handlers call the targets
(``omniscs.viewer.targets``), ``state`` and ``session``; nothing here decides what is drawn or what an edit means."""
from __future__ import annotations

import threading
from pathlib import Path
from typing import Callable

import numpy as np

from omniscs.errors import OmniscsError
from omniscs.geometry import make_transform
from omniscs.nsg.graph import BACKGROUND
from omniscs.quaternions import quat_to_rotmat, rotmat_to_quat
from omniscs.viewer.state import EGO_COLOUR, FrameState, ViewerConfig, box_colour
from omniscs.viewer.targets import GraphTarget, StoreTarget


# ----------------------------------------------------------------------------- viser wiring
def pose_args(T: np.ndarray) -> dict:  # [4, 4] -> viser's wxyz/position keywords
    return {"wxyz": rotmat_to_quat(T[:3, :3]), "position": np.asarray(T[:3, 3], dtype=np.float64)}


def pose_from_gizmo(wxyz, position) -> np.ndarray:  # viser's (w, x, y, z), (x, y, z) -> [4, 4] float64
    return make_transform(quat_to_rotmat(np.asarray(wxyz, dtype=np.float64)), np.asarray(position, dtype=np.float64))


#: Entry of the agent list when no agent is selected.
NO_AGENT = "(none)"
#: Entry of the variant list that shows the log.
NO_VARIANT = "(the log)"
#: How an inserted model lies: its roll about its own forward axis (degrees), resting on the ground.
LIE_ROLL_DEG = {"upright": 0.0, "on its side": 90.0, "overturned": 180.0}


class ViewerApp:
    """One target served by one viser server: builds the scene and panel and keeps them in step with the frame,
    the camera and the edits. Every handler takes the lock: viser runs them on a thread pool."""

    def __init__(self, server, target: GraphTarget | StoreTarget, frame: int = 0,
                 config: ViewerConfig | None = None, edits_out: Path | None = None) -> None:
        self.server = server
        self.target = target
        self.config = config or ViewerConfig()
        self.lock = threading.RLock()
        self.selected: int | None = None
        self._boxes: dict[int, object] = {}
        self._labels: dict[int, tuple[str, tuple]] = {}
        self._splats: dict[str, object] = {}
        self._frustums: dict[str, object] = {}
        self._gizmo = None
        self._path_handles: list = []             # control points of the selected agent's path, while drawn
        self._path_frames = np.zeros(0, np.int64)  # their frames
        self._stop = threading.Event()
        start = int(frame)
        if not 0 <= start < target.n_frames:
            raise OmniscsError(f"--frame {frame} is out of range: {target.scene_id} has frames 0 to "
                               f"{target.n_frames - 1}")
        self._build_panel(start, edits_out or Path(f"{target.scene_id}-edits.json"))
        self._build_scene(start)
        self._player = threading.Thread(target=self._play_loop, name="omniscs-view-play", daemon=True)
        self._player.start()

    # -- panel ------------------------------------------------------------------------------
    def _build_panel(self, frame: int, edits_out: Path) -> None:
        gui = self.server.gui
        t = self.target
        self.summary = gui.add_markdown(t.summary())
        if getattr(t, "samples", None):
            with gui.add_folder("Samples"):
                self.sample_list = gui.add_dropdown("Variant store", [r["store_id"] for r in t.samples],
                                                    initial_value=t.samples[0]["store_id"])
                self.sample_figures = gui.add_markdown(t.sample_summary())
                self.frame_figures = gui.add_markdown(t.frame_summary(frame))
            self.sample_list.on_update(lambda _: self.pick_sample(self.sample_list.value))
        with gui.add_folder("Time"):
            self.frame_slider = gui.add_slider("Frame", min=0, max=max(t.n_frames - 1, 1), step=1, initial_value=frame,
                                               disabled=t.n_frames < 2)
            self.play = gui.add_checkbox("Play", False, disabled=t.n_frames < 2)
            # a target with figures per frame (a closed-loop run's step) shows them under the slider
            self.step_figures = gui.add_markdown(t.step_summary(frame)) if hasattr(t, "step_summary") else None
        with gui.add_folder("Camera view"):
            self.camera = gui.add_dropdown("Camera", t.camera_names, initial_value=t.camera_names[0])
            self.draw_boxes = gui.add_checkbox("Boxes on image", True)
            self.image = gui.add_image(np.zeros((2, 2, 3), np.uint8), label="camera view", format="jpeg")
        if t.layers:
            share = max(1, min(100, round(100 * t.config.splat_budget / max(t.n_gaussians, 1))))
            with gui.add_folder("Splats", expand_by_default=False):
                self.splat_share = gui.add_slider("Drawn (%)", min=1, max=100, step=1, initial_value=share,
                                                  hint="The most opaque Gaussians are kept; fewer redraw faster")
            self.splat_share.on_update(lambda _: self.set_splat_share(int(self.splat_share.value)))
        self.frame_slider.on_update(lambda _: self.refresh())
        self.camera.on_update(lambda _: self.refresh_image())
        self.draw_boxes.on_update(lambda _: self.refresh_image())
        if not t.editable:
            return
        if t.variants:
            with gui.add_folder("Variants"):
                ids = [str(v["variant_id"]) for v in t.variants]
                self.variant_list = gui.add_dropdown("Variant", [NO_VARIANT] + ids, initial_value=NO_VARIANT)
                self.variant_figures = gui.add_markdown("The log as recorded.")
            self.variant_list.on_update(lambda _: self.pick_variant(self.variant_list.value))
        with gui.add_folder("Edit agents"):
            self.agent_list = gui.add_dropdown("Agent", [NO_AGENT] + self._agent_labels(), initial_value=NO_AGENT)
            self.remove_button = gui.add_button("Remove agent", disabled=True)
            self.path_toggle = gui.add_checkbox("Draw its path", False, disabled=True,
                                                hint="Drag the points of its path (a cut-in: move the later ones "
                                                     "into the ego's lane)")
            self.reset_button = gui.add_button("Reset agent", disabled=True)
            self.edits_path = gui.add_text("Save to", str(edits_out))
            self.save_button = gui.add_button("Save edits")
            self.status = gui.add_markdown("No edits yet. Pick an agent, drag or turn its gizmo.")
        self.agent_list.on_update(lambda _: self.select(self._track_of(self.agent_list.value)))
        self.remove_button.on_click(lambda _: self.remove_selected())
        self.path_toggle.on_update(lambda _: self.show_path(bool(self.path_toggle.value)))
        self.reset_button.on_click(lambda _: self.reset_selected())
        self.save_button.on_click(lambda _: self.save())
        # the controls that act on the selected agent, enabled while one is
        self._per_agent = [self.remove_button, self.reset_button, self.path_toggle]
        self._models = {f"{model_id} {category}": (model_id, category) for model_id, category in t.models()}
        if not self._models:  # a graph without agent nodes, and no --pool
            return
        with gui.add_folder("Models", expand_by_default=False):
            self.model_list = gui.add_dropdown("Model", list(self._models), initial_value=next(iter(self._models)))
            self.lie = gui.add_dropdown("Lies", list(LIE_ROLL_DEG), initial_value="upright")
            self.replace_button = gui.add_button("Give the agent this model", disabled=True)
            self.insert_button = gui.add_button("Insert: click the road")
        self._per_agent.append(self.replace_button)
        self.replace_button.on_click(lambda _: self.replace_selected())
        self.insert_button.on_click(lambda _: self.arm_insert())

    def _agent_labels(self) -> list[str]:
        return [f"{a.track_id} {a.category}" for a in self.target.session.graph.agents]

    @staticmethod
    def _track_of(label: str) -> int | None:
        return None if label == NO_AGENT else int(label.split(" ", 1)[0])

    # -- scene ------------------------------------------------------------------------------
    def _build_scene(self, frame: int) -> None:
        scene = self.server.scene
        for key, splats in self.target.layers.items():
            if len(splats):
                self._splats[key] = scene.add_gaussian_splats(f"/splats/{key}", centers=splats.centers,
                                                              covariances=splats.covariances, rgbs=splats.rgbs,
                                                              opacities=splats.opacities, visible=key == BACKGROUND)
        ego = self.target.frame_state(frame).world_from_ego
        # behind and above the ego, looking down the road: the view a driver knows
        self.server.initial_camera.position = tuple(ego[:3, :3] @ np.array([-14.0, 0.0, 9.0]) + ego[:3, 3])
        self.server.initial_camera.look_at = tuple(ego[:3, :3] @ np.array([12.0, 0.0, 0.0]) + ego[:3, 3])
        road = self.target.road()
        if road is not None and len(road[0]):
            scene.add_line_segments("/road", road[0].astype(np.float32), road[1], thickness=1.5,
                                    thickness_units="screen")
        self.refresh_trajectories()
        self.refresh()

    def refresh_trajectories(self) -> None:
        """The paths as line segments between consecutive present frames, in their track's colour."""
        segments, colours = [], []
        for traj in self.target.trajectories():
            p = traj.positions
            if len(p) < 2:
                continue
            segments.append(np.stack([p[:-1], p[1:]], 1))
            colours.append(np.tile(np.array(traj.colour, np.uint8), (len(p) - 1, 2, 1)))
        if segments:
            self.server.scene.add_line_segments("/trajectories", np.concatenate(segments).astype(np.float32),
                                                np.concatenate(colours), thickness=2.0, thickness_units="screen")
        else:
            self.server.scene.remove_by_name("/trajectories")

    def refresh(self) -> None:
        """The 3D scene and the camera view at the slider's frame."""
        with self.lock:
            frame = int(self.frame_slider.value)
            state = self.target.frame_state(frame)
            with self.server.atomic():
                self._place_nodes(state)
                self._place_boxes(state)
                self._place_rig(state)
                if state.points is not None:
                    self.server.scene.add_point_cloud("/lidar", state.points, _height_colours(state.points),
                                                      point_size=0.06)
                self._place_gizmo(state)
            if getattr(self.target, "samples", None):
                self.frame_figures.content = self.target.frame_summary(frame)
            if self.step_figures is not None:
                self.step_figures.content = self.target.step_summary(frame)
            self.refresh_image()

    def refresh_image(self) -> None:
        with self.lock:
            self.image.image = self.target.camera_image(self.camera.value, int(self.frame_slider.value),
                                                        bool(self.draw_boxes.value), self.selected)

    def _place_nodes(self, state: FrameState) -> None:
        shown = {n.key: n.world_from_node for n in state.nodes}
        for key, handle in self._splats.items():
            if key in shown:
                pose = pose_args(shown[key])
                handle.wxyz, handle.position = pose["wxyz"], pose["position"]
            handle.visible = key in shown

    def _place_boxes(self, state: FrameState) -> None:
        shown = set()
        for box in state.boxes:
            shown.add(box.track_id)
            colour = box_colour(box, self.selected, getattr(self.target, "adversary", None))
            handle = self._boxes.get(box.track_id)
            if handle is None:
                handle = self.server.scene.add_box(f"/boxes/{box.track_id}", color=colour, dimensions=tuple(box.size),
                                                   wireframe=True, **pose_args(box.world_from_box))
                handle.on_click(lambda event, tid=box.track_id: self.select(tid))
                self._boxes[box.track_id] = handle
            else:
                pose = pose_args(box.world_from_box)
                handle.wxyz, handle.position = pose["wxyz"], pose["position"]
                handle.color, handle.dimensions = colour, tuple(box.size)
            # the label floats above the box whichever way the box lies: world up, in the box's frame
            above = box.world_from_box[:3, :3].T @ np.array([0.0, 0.0, 0.5 * float(box.size.max()) + 0.3])
            label = (box.label, tuple(np.round(above, 2)))
            if self._labels.get(box.track_id) != label:  # new, or a new model, size or tilt
                self._labels[box.track_id] = label
                self.server.scene.add_label(f"/boxes/{box.track_id}/label", box.label, position=label[1])
            handle.visible = True
        for tid, handle in self._boxes.items():
            if tid not in shown:
                handle.visible = False

    def _place_rig(self, state: FrameState) -> None:
        ego = pose_args(state.world_from_ego)
        if "/ego" not in self._frustums:
            self._frustums["/ego"] = self.server.scene.add_frame("/ego", axes_length=1.5, axes_radius=0.05, **ego)
        for f in state.frustums:
            pose = pose_args(f.world_from_camera)
            if f.camera not in self._frustums:
                self._frustums[f.camera] = self.server.scene.add_camera_frustum(
                    f"/cameras/{f.camera}", fov=f.fov_y, aspect=f.aspect, scale=self.config.frustum_scale_m,
                    color=EGO_COLOUR, **pose)
        for name, handle in self._frustums.items():
            pose = ego if name == "/ego" else pose_args(next(f.world_from_camera for f in state.frustums
                                                              if f.camera == name))
            handle.wxyz, handle.position = pose["wxyz"], pose["position"]

    # -- edits ------------------------------------------------------------------------------
    def select(self, track_id: int | None) -> None:
        """Make ``track_id`` the selected agent (None: none): its gizmo appears, its box turns white."""
        with self.lock:
            if not self.target.editable:
                return
            self.selected = track_id if track_id is not None and self.target.session.editable(track_id) else None
            label = NO_AGENT if self.selected is None else next(
                (l for l in self.agent_list.options if self._track_of(l) == self.selected), NO_AGENT)
            if self.agent_list.value != label:
                self.agent_list.value = label  # calls select again, with the same track: harmless
            for control in self._per_agent:
                control.disabled = self.selected is None
            self.path_toggle.value = False  # a new selection starts without its path's handles
            self.show_path(False)
            self.refresh()

    def _place_gizmo(self, state: FrameState) -> None:
        box = next((b for b in state.boxes if b.track_id == self.selected), None) if self.target.editable else None
        if box is None:
            if self._gizmo is not None:
                self._gizmo.remove()
                self._gizmo = None
            return
        pose = pose_args(box.world_from_box)
        if self._gizmo is None:
            self._gizmo = self.server.scene.add_transform_controls("/gizmo", scale=max(2.0, float(box.size.max())),
                                                                   depth_test=False, **pose)
            self._gizmo.on_update(self._on_gizmo)
        else:
            self._gizmo.wxyz, self._gizmo.position = pose["wxyz"], pose["position"]

    def show_path(self, on: bool) -> None:
        """Show (or hide) the selected agent's path as draggable control points, on the ground plane of its
        poses; a release gives the agent the path through them (``set_path``)."""
        from omniscs.viewer.paths import control_frames

        with self.lock:
            for handle in self._path_handles:
                handle.remove()
            self._path_handles = []
            if not on or self.selected is None:
                return
            node = self.target.session.graph.agent(self.selected)
            self._path_frames = control_frames(node.present)
            for k, f in enumerate(self._path_frames):
                handle = self.server.scene.add_transform_controls(
                    f"/path/{k}", scale=1.2, active_axes=(True, True, False), disable_rotations=True,
                    depth_test=False, position=tuple(node.world_from_agent[f, :3, 3]))
                handle.on_update(self._on_path_point)
                self._path_handles.append(handle)

    def _on_path_point(self, event) -> None:
        if event.phase == "end":
            self.draw_path(np.array([h.position[:2] for h in self._path_handles], dtype=np.float64))

    def draw_path(self, control_xy: np.ndarray) -> None:  # [K, 2] world, one per control frame
        """The selected agent follows the path through ``control_xy`` (the handler of a control point's release)."""
        from omniscs.viewer.paths import path_waypoints

        with self.lock:
            if self.selected is None:
                return
            node = self.target.session.graph.agent(self.selected)
            try:
                waypoints = path_waypoints(node.world_from_agent, node.present, self._path_frames, control_xy)
                self.target.session.set_path(self.selected, waypoints)
            except OmniscsError as exc:
                self.status.content = f"Path refused: {exc}"
                return
            self._edited()
            self._say_placement(self.selected)

    def _on_gizmo(self, event) -> None:
        """While dragging, the agent's splats and box follow the gizmo; at release the move becomes an edit."""
        gizmo = event.target
        with self.lock:
            if self.selected is None:
                return
            pose = pose_from_gizmo(gizmo.wxyz, gizmo.position)
            key = f"agent.{self.selected}"
            live = pose_args(pose)
            for handle in (self._splats.get(key), self._boxes.get(self.selected)):
                if handle is not None:
                    handle.wxyz, handle.position = live["wxyz"], live["position"]
            if event.phase == "end":
                self.move_selected(pose)

    def move_selected(self, world_from_box: np.ndarray) -> None:
        """The selected agent put at ``world_from_box`` at the current frame (the handler of a gizmo release)."""
        with self.lock:
            if self.path_toggle.value:
                self.path_toggle.value = False  # the path moves with the agent: its points are drawn again
            try:
                self.target.session.move(self.selected, int(self.frame_slider.value), world_from_box)
            except OmniscsError as exc:
                self.refresh()  # the agent and its gizmo go back where the session has them
                self.status.content = f"Move refused: {exc}"
                return
            self._edited()
            self._say_placement(self.selected)

    def _say_placement(self, track_id: int) -> None:
        verdict = self.target.placement_verdict(track_id)
        if verdict:
            self.status.content += f"\n\n{verdict}"

    def remove_selected(self) -> None:
        with self.lock:
            if self.selected is None:
                return
            self.target.session.remove(self.selected)
            self.selected = None
            self.agent_list.value = NO_AGENT
            for control in self._per_agent:
                control.disabled = True
            self._edited()

    def reset_selected(self) -> None:
        with self.lock:
            if self.selected is not None:
                self.target.session.reset(self.selected)
                self._edited()

    def replace_selected(self) -> None:
        """The selected agent gets the model picked in the panel (scaled to its box)."""
        with self.lock:
            if self.selected is None:
                return
            model_id, _ = self._models[self.model_list.value]
            try:
                self.target.session.replace_model(self.selected, model_id)
            except OmniscsError as exc:
                self.status.content = f"Model not changed: {exc}"
                return
            self._edited()
            self._say_placement(self.selected)

    def arm_insert(self) -> None:
        """The next click on the road inserts the model picked in the panel there."""
        def clicked(event) -> None:
            self.server.scene.remove_click_callback(clicked)
            point = self.target.ground_point(event.ray_origin, event.ray_direction, int(self.frame_slider.value))
            if point is None:
                self.status.content = "That click missed the road (it points above the horizon); insert again."
                return
            self.insert_at(*point)

        self.server.scene.on_click()(clicked)
        self.status.content = "Click the road where the model should stand."

    def insert_at(self, x: float, y: float, ground_z: float) -> int | None:
        """Insert the model picked in the panel standing at (x, y) on the ground at ``ground_z``, lying as picked,
        headed along the lane (or the ego); it becomes the selected agent. Returns its track id."""
        with self.lock:
            model_id, category = self._models[self.model_list.value]
            frame = int(self.frame_slider.value)
            try:
                heading = self.target.heading_at(x, y, frame)
                tid = self.target.session.insert(model_id, category, x, y, ground_z, heading,
                                                 LIE_ROLL_DEG[self.lie.value])
            except OmniscsError as exc:
                self.status.content = f"Not inserted: {exc}"
                return None
            self._edited()
            self.select(tid)
            self._say_placement(tid)
            return tid

    def save(self) -> Path | None:
        """Write the session's spec to the path in the panel; the panel says where, or why not."""
        with self.lock:
            try:
                path = self.target.session.save(Path(self.edits_path.value))
            except OmniscsError as exc:
                self.status.content = f"Not saved: {exc}"
                return None
            n = len(self.target.session.edits())
            pool = f" --pool {self.target.pool}" if self.target.pool is not None else ""
            self.status.content = f"Saved {n} edit(s) to `{path}`. Render them: `omniscs render {self.target.path} " \
                                  f"--edit @{path}{pool} --out edited.png`; make them a dataset: `omniscs generate " \
                                  f"SOURCE --fit-preset fast --edit @{path}{pool} --annotate`"
            return path

    def pick_sample(self, store_id: str) -> None:
        """Show the dataset's variant store ``store_id``: its frames, cameras, boxes, LiDAR and images."""
        with self.lock:
            ids = [r["store_id"] for r in self.target.samples]
            self.target.pick(ids.index(store_id))
            self.sample_figures.content = self.target.sample_summary()
            for handle in self._boxes.values():  # another store: other tracks
                handle.remove()
            self._boxes.clear()
            self._labels.clear()
            for handle in self._frustums.values():
                handle.remove()
            self._frustums.clear()
            last = max(self.target.n_frames - 1, 1)
            if int(self.frame_slider.value) > last:
                self.frame_slider.value = 0
            self.frame_slider.max = last
            self.camera.options = self.target.camera_names  # the picked camera stays when the store has it
            road = self.target.road()
            if road is not None and len(road[0]):
                self.server.scene.add_line_segments("/road", road[0].astype(np.float32), road[1], thickness=1.5,
                                                    thickness_units="screen")
            else:
                self.server.scene.remove_by_name("/road")
            self.refresh_trajectories()
            self.refresh()

    def pick_variant(self, variant_id: str) -> None:
        """Show the variant ``variant_id`` (``NO_VARIANT``: the log): its agents, its ego, its adversary in red, the
        log's paths in grey beneath its own; edits made before are dropped, later ones add to the variant's."""
        from omniscs.viewer.variants import variant_summary

        with self.lock:
            ids = [str(v["variant_id"]) for v in self.target.variants]
            index = None if variant_id == NO_VARIANT else ids.index(variant_id)
            try:
                self.target.pick_variant(index)
            except OmniscsError as exc:
                self.variant_figures.content = f"Cannot show {variant_id}: {exc}"
                return
            self.variant_figures.content = "The log as recorded." if index is None else \
                variant_summary(self.target.variants[index])
            self.selected = None
            self.agent_list.value = NO_AGENT
            self._edited()

    def set_splat_share(self, percent: int) -> None:
        """Draw ``percent`` % of the graph's Gaussians, the most opaque (the level-of-detail control)."""
        with self.lock:
            budget = max(1, round(self.target.n_gaussians * percent / 100))
            self._send_layers(self.target.set_budget(budget))
            self.summary.content = self.target.summary()
            self.refresh()

    def _send_layers(self, keys) -> None:
        """(Re)send the splat layers ``keys`` (a new model, a new agent, a new budget); an empty layer is removed."""
        for key in keys:
            splats = self.target.layers[key]
            old = self._splats.pop(key, None)
            if old is not None:
                old.remove()
            if len(splats):
                self._splats[key] = self.server.scene.add_gaussian_splats(
                    f"/splats/{key}", centers=splats.centers, covariances=splats.covariances, rgbs=splats.rgbs,
                    opacities=splats.opacities, visible=False)  # refresh() shows and places it

    def _edited(self) -> None:
        n = len(self.target.session.edits())
        self.status.content = f"{n} edit(s), not saved yet." if n else "No edits."
        self._send_layers(self.target.changed_layers())  # a model changed, or an agent came or went
        options = [NO_AGENT] + self._agent_labels()
        if tuple(self.agent_list.options) != tuple(options):
            self.agent_list.options = options
        self.refresh_trajectories()
        self.refresh()

    # -- play -------------------------------------------------------------------------------
    def _play_loop(self) -> None:
        while not self._stop.wait(1.0 / self.config.play_fps):
            if self.play.value and self.target.n_frames > 1:
                try:
                    self.frame_slider.value = (int(self.frame_slider.value) + 1) % self.target.n_frames
                except Exception:  # noqa: BLE001 - a client gone mid-update must not end playback for the others
                    continue

    def close(self) -> None:
        self._stop.set()
        self._player.join(timeout=2.0)


def _height_colours(points: np.ndarray) -> np.ndarray:  # [M, 3] world -> uint8 [M, 3]
    """LiDAR points coloured by height above the lowest return: blue (ground) to yellow (4 m up)."""
    h = np.clip((points[:, 2] - points[:, 2].min()) / 4.0, 0.0, 1.0)[:, None] if len(points) else np.zeros((0, 1))
    low, high = np.array([40, 90, 200]), np.array([250, 220, 40])
    return (low + h * (high - low)).astype(np.uint8)


def check_host(host: str) -> None:
    """Refuse an address this machine cannot listen on (viser waits forever for one), in one line."""
    import socket

    try:
        infos = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)
    except socket.gaierror as exc:
        raise OmniscsError(f"--host {host} does not resolve ({exc.strerror}); give an address of this machine, e.g. "
                           "127.0.0.1") from None
    family, kind, proto, _, address = infos[0]
    try:
        with socket.socket(family, kind, proto) as probe:
            probe.bind(address)
    except OSError as exc:
        raise OmniscsError(f"cannot listen on {host} ({exc.strerror or exc}); give an address of this machine, e.g. "
                           "127.0.0.1") from None


def serve(target: GraphTarget | StoreTarget, host: str = "127.0.0.1", port: int = 8080, frame: int = 0,
          config: ViewerConfig | None = None, edits_out: Path | None = None,
          ready: Callable[[str], None] | None = None, stop: threading.Event | None = None) -> None:
    """Serve ``target`` at http://host:port until Ctrl-C (KeyboardInterrupt), ``stop`` is set, or a stage's
    ``Stopped``; the server is closed on the way out. ``ready`` gets the URL once the viewer is up."""
    import viser

    check_host(host)
    server = viser.ViserServer(host=host, port=port, label=f"omniscs view {target.scene_id}", verbose=False)
    app = None
    try:
        app = ViewerApp(server, target, frame, config, edits_out)
        if ready:
            ready(f"http://{host}:{server.get_port()}")
        stop = stop or threading.Event()
        while not stop.wait(0.5):
            pass
    finally:
        if app is not None:
            app.close()
        server.stop()
