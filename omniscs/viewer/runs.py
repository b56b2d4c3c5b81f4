"""A closed-loop run folder (``omniscs closedloop run --out``) replayed step by step in the viewer: the ego's box and
its driven path beside the scenario's reference, the agents' boxes as the simulator had them (those the ego touched
red from the contact on), the camera frame the policy saw, the run's scores and each step's figures. A folder written
before runs kept replay.json and its frames shows what it has: the ego's path from steps.json."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omniscs.errors import OmniscsError
from omniscs.geometry import pose_from_xyz_yaw
from omniscs.scene.store import CameraRecord
from omniscs.viewer.state import (ADVERSARY_COLOUR, EGO_COLOUR, AgentBox, FrameState, Splats, Trajectory,
                                  ViewerConfig, category_colour, frustum, road_lines, with_boxes)

#: Track id of the ego's box among a step's boxes (real track ids are never negative).
EGO_TRACK = -1
#: Colour of a box at and after its contact with the ego (and of the ego's box at a contact step).
CONTACT_COLOUR = ADVERSARY_COLOUR
#: Colour of the scenario's reference ego path under the driven one.
REFERENCE_COLOUR = (150, 150, 150)
#: Size (width, height) of the camera panel's notice when a step has no kept frame.
NOTICE_SIZE = (480, 270)
#: What to do about a run folder that cannot be replayed.
RUN_AGAIN = "write the run again (omniscs closedloop run SCENARIO --out DIR)"


@dataclass(frozen=True)
class Replay:
    """replay.json of a run folder (``omniscs.closedloop.run.replay_record``), as arrays."""

    camera: str | None                      # the camera whose frames were kept
    frames: tuple[Path | None, ...]         # [T] the frame file of each step (None: none kept)
    ego_size: np.ndarray                    # [3] length, width, height (metres)
    centre_ahead_m: float                   # the ego box centre lies this far ahead of the ego frame's origin
    ground_z: np.ndarray                    # [T] height of the ego frame's origin (metres)
    track_ids: np.ndarray                   # [N] int64
    categories: tuple[str, ...]             # [N]
    sizes: np.ndarray                       # [N, 3] length, width, height (metres)
    agents: tuple[np.ndarray, ...]          # [T] of [n_k, 5]: row into the tracks, x, y, z, yaw (box centres, world)
    contacts: tuple[frozenset[int], ...]    # [T] track ids the ego touched at that step
    rig: tuple[CameraRecord, ...]           # the cameras as rendered
    frame_size: tuple[int, int] | None      # (width, height) of the kept frames
    reference: np.ndarray                   # [S, 3] x, y, yaw of the scenario's reference ego box centre
    road: dict | None                       # the scenario's road map (``RoadMap.to_dict``), or None


def read_run(path: Path) -> tuple[dict, list[dict], Replay | None]:
    """(run.json, steps.json's rows, replay.json or None when the run predates it) of the run folder ``path``;
    a missing or damaged run.json or steps.json, or a damaged replay.json, is one OmniscsError."""
    from omniscs.closedloop.run import REPLAY_JSON, RUN_JSON, STEPS_JSON
    from omniscs.untrusted import read_json, read_own_json

    damaged = f"the run folder {path} is damaged; {RUN_AGAIN}"
    run = read_own_json(path / RUN_JSON, damaged, expect=dict, what="run record")
    if not (path / STEPS_JSON).is_file():
        raise OmniscsError(f"{path} has {RUN_JSON} but no {STEPS_JSON}: its steps were not written; {RUN_AGAIN}")
    steps = read_json(path / STEPS_JSON, damaged, expect=list, what="run steps")
    for k, row in enumerate(steps):
        if not (isinstance(row, dict) and all(isinstance(row.get(key), (int, float)) and not isinstance(
                row.get(key), bool) for key in ("x", "y", "yaw", "speed"))):
            raise OmniscsError(f"{path / STEPS_JSON}: step {k} has no numeric x, y, yaw and speed; {damaged}")
    if not steps:
        raise OmniscsError(f"{path / STEPS_JSON} holds no steps; {damaged}")
    if not (path / REPLAY_JSON).is_file():
        return run, steps, None
    record = read_json(path / REPLAY_JSON, damaged, expect=dict, what="run replay")
    try:
        replay = _replay(record, path, len(steps))
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise OmniscsError(f"{path / REPLAY_JSON} does not hold a replay of {len(steps)} steps ({exc}); {damaged}") \
            from None
    return run, steps, replay


def _replay(record: dict, path: Path, n_steps: int) -> Replay:
    from omniscs.closedloop.run import REPLAY_VERSION

    if record.get("version") != REPLAY_VERSION:
        raise ValueError(f"layout version {record.get('version')!r}, this omniscs reads {REPLAY_VERSION}")
    tracks = record["tracks"]
    agents = tuple(np.asarray(step, np.float64).reshape(-1, 5) for step in record["agents"])
    frames = tuple(None if f is None else path / str(f) for f in record["frames"])
    ground = np.asarray(record["ego"]["ground_z"], np.float64)
    if not (len(agents) == len(frames) == len(ground) == len(record["contacts"]) == n_steps):
        raise ValueError("its per-step lists are not one per step")
    if any(len(a) and (a[:, 0].min() < 0 or a[:, 0].max() >= len(tracks)) for a in agents):
        raise ValueError("an agent names a track it does not list")
    if any(f is not None and path.resolve() not in f.resolve().parents for f in frames):
        raise ValueError("a frame lies outside the run folder")
    rig = tuple(CameraRecord(str(c["name"]), int(c["width"]), int(c["height"]), np.asarray(c["K"], np.float64)
                             .reshape(3, 3), np.asarray(c["ego_from_camera"], np.float64).reshape(4, 4))
                for c in record["rig"])
    size = record.get("frame_size")
    ego = record["ego"]
    return Replay(
        camera=None if record.get("camera") is None else str(record["camera"]), frames=frames,
        ego_size=np.array([ego["length"], ego["width"], ego["height"]], np.float64),
        centre_ahead_m=float(ego["centre_ahead_m"]), ground_z=ground,
        track_ids=np.array([int(t["track_id"]) for t in tracks], np.int64),
        categories=tuple(str(t["category"]) for t in tracks),
        sizes=np.array([t["size"] for t in tracks], np.float64).reshape(-1, 3), agents=agents,
        contacts=tuple(frozenset(int(t) for t in c) for c in record["contacts"]), rig=rig,
        frame_size=None if size is None else (int(size[0]), int(size[1])),
        reference=np.asarray(record["reference"], np.float64).reshape(-1, 3),
        road=record.get("road") if isinstance(record.get("road"), dict) else None)


class ClosedLoopRunTarget:
    """A closed-loop run folder: one frame per step of the run; nothing to edit."""

    kind = "closed-loop run"
    editable = False

    def __init__(self, path: Path, config: ViewerConfig) -> None:
        self.path = path
        self.config = config
        self.run, self.steps, self.replay = read_run(path)
        self.layers: dict[str, Splats] = {}
        self.scene_id = str(self.run.get("scene_id") or path.name)
        self.n_frames = len(self.steps)
        # [T, 3] x, y, yaw of the ego box centre at each step, as steps.json records it
        self.ego = np.array([[row["x"], row["y"], row["yaw"]] for row in self.steps], np.float64)
        r = self.replay
        self.ground_z = r.ground_z if r is not None else np.zeros(self.n_frames)
        self.first_contact: dict[int, int] = {}  # track id -> the first step the ego touched it
        for k, touched in enumerate(r.contacts if r is not None else ()):
            for tid in touched:
                self.first_contact.setdefault(tid, k)
        cameras = [str(c) for c in self.run.get("cameras") or []]
        self.camera_names = [r.camera] if r is not None and r.camera is not None else cameras[:1] or ["camera"]
        self._frame_cache: tuple[int, np.ndarray] | None = None

    # -- one step -------------------------------------------------------------------------------
    def world_from_ego(self, step: int) -> np.ndarray:  # -> [4, 4] the ego frame (rear axle, on the ground)
        x, y, yaw = self.ego[step]
        ahead = 0.0 if self.replay is None else self.replay.centre_ahead_m
        return pose_from_xyz_yaw(x - ahead * math.cos(yaw), y - ahead * math.sin(yaw), float(self.ground_z[step]),
                                 yaw)

    def frame_state(self, frame: int) -> FrameState:
        """Step ``frame``: the ego's box (red at a contact), the agents present (red from their contact with the
        ego on), the rig's frustums; a run without replay.json: the ego frame alone."""
        k = self._check(frame)
        ego = self.world_from_ego(k)
        r = self.replay
        if r is None:
            return FrameState(k, ego, (), (), ())
        x, y, yaw = self.ego[k]
        touched = bool(r.contacts[k]) or bool(self.steps[k].get("collision"))
        boxes = [AgentBox(EGO_TRACK, "ego", pose_from_xyz_yaw(x, y, float(self.ground_z[k]) + 0.5 * r.ego_size[2], yaw),
                          r.ego_size.copy(), CONTACT_COLOUR if touched else EGO_COLOUR)]
        for row, ax, ay, az, ayaw in r.agents[k]:
            i = int(row)
            tid = int(r.track_ids[i])
            hit = self.first_contact.get(tid, self.n_frames) <= k
            boxes.append(AgentBox(tid, r.categories[i], pose_from_xyz_yaw(ax, ay, az, ayaw), r.sizes[i].copy(),
                                  CONTACT_COLOUR if hit else category_colour(r.categories[i])))
        return FrameState(k, ego, (), tuple(boxes), tuple(frustum(c, ego) for c in r.rig))

    def trajectories(self) -> tuple[Trajectory, ...]:
        """The ego's driven path, the scenario's reference path (grey), then each agent's path over the run."""
        steps = np.arange(self.n_frames)
        out = [Trajectory(None, "ego", np.concatenate([self.ego[:, :2], self.ground_z[:, None]], 1), steps)]
        r = self.replay
        if r is None:
            return tuple(out)
        ground = float(np.median(self.ground_z))
        out.append(Trajectory(None, "reference", np.concatenate(
            [r.reference[:, :2], np.full((len(r.reference), 1), ground)], 1), np.arange(len(r.reference)),
            tint=REFERENCE_COLOUR))
        paths: dict[int, list] = {}
        for k, rows in enumerate(r.agents):
            for row in rows:
                paths.setdefault(int(row[0]), []).append((k, row[1:4]))
        for i in sorted(paths):
            ks, xyz = zip(*paths[i])
            out.append(Trajectory(int(r.track_ids[i]), r.categories[i], np.array(xyz, np.float64),
                                  np.array(ks, np.int64)))
        return tuple(out)

    def camera_image(self, camera: str, frame: int, boxes: bool, highlight: int | None = None) -> np.ndarray:
        """The frame the policy saw at step ``frame`` (uint8 [H, W, 3]), with the step's boxes drawn when
        ``boxes``; a notice picture when the run kept none."""
        k = self._check(frame)
        image = self.observed_frame(k)
        if image is None:
            return notice_image(self.missing_frame_reason(k))
        if not boxes:
            return image
        camera_record = self._frame_camera(image.shape[1], image.shape[0])
        if camera_record is None:
            return image
        state = self.frame_state(k)
        others = tuple(b for b in state.boxes if b.track_id != EGO_TRACK)
        return with_boxes(image, camera_record, state.world_from_ego, others, highlight)

    def observed_frame(self, step: int) -> np.ndarray | None:  # -> uint8 [H, W, 3], or None when none was kept
        """The kept camera frame of ``step`` as written (JPEG), or None."""
        if self._frame_cache is not None and self._frame_cache[0] == step:
            return self._frame_cache[1].copy()
        file = None if self.replay is None else self.replay.frames[step]
        if file is None or not file.is_file():
            return None
        from PIL import Image, UnidentifiedImageError

        try:
            with Image.open(file) as picture:
                image = np.asarray(picture.convert("RGB"), dtype=np.uint8)
        except (OSError, UnidentifiedImageError) as exc:
            raise OmniscsError(f"{file} is not a readable image ({exc}); {RUN_AGAIN}") from None
        self._frame_cache = (step, image)
        return image.copy()

    def missing_frame_reason(self, step: int) -> str:
        if self.replay is None:
            return "This run folder kept no camera frames (written before runs kept them); replay.gif shows them."
        if self.replay.frames[step] is None:
            return f"No camera frame was kept for step {step}."
        return f"The frame of step {step} ({self.replay.frames[step].name}) is missing from the run folder."

    def _frame_camera(self, width: int, height: int) -> CameraRecord | None:
        """The kept camera with its intrinsics scaled to a frame of ``width`` x ``height`` pixels."""
        cam = next((c for c in self.replay.rig if c.name == self.replay.camera), None) if self.replay else None
        if cam is None:
            return None
        K = cam.K.copy()
        K[0] *= width / cam.width
        K[1] *= height / cam.height
        return CameraRecord(cam.name, width, height, K, cam.ego_from_camera)

    def road(self) -> tuple[np.ndarray, np.ndarray] | None:
        if self.replay is None or self.replay.road is None:
            return None
        from omniscs.roadmap import RoadMap

        return road_lines(RoadMap.from_dict(self.replay.road), float(np.median(self.ground_z)))

    # -- words ----------------------------------------------------------------------------------
    def summary(self) -> str:
        """The run in Markdown: what ran, how it ended, PDMS, EPDMS and HD-Score with their sub-scores."""
        run = self.run
        hit = run.get("collided_with") or []
        lines = [f"**{run.get('scenario_id', self.scene_id)}** ({self.kind}): policy {run.get('policy', '?')}, "
                 f"{self.n_frames} steps of {_num(run.get('dt'), 2)} s, ended by {run.get('reason', '?')}"
                 + (f", touched {', '.join(str(t) for t in hit)} (red)" if hit else "")
                 + ("" if run.get("adversary") is None else f"; adversary {run['adversary']}")]
        if self.replay is None:
            lines.append("*Written before runs kept agents and frames: the ego's path only.*")
        lines.append("\n" + scores_markdown(run.get("scores") if isinstance(run.get("scores"), dict) else {}))
        return "\n".join(lines)

    def step_summary(self, frame: int) -> str:
        """Step ``frame``'s figures in Markdown: time, speed, controls, contact, off-road, its per-step scores."""
        k = self._check(frame)
        row = self.steps[k]
        touched = sorted(self.replay.contacts[k]) if self.replay is not None else []
        contact = ("yes" + (f" (track {', '.join(str(t) for t in touched)})" if touched else "")
                   if row.get("collision") else "no")
        parts = [f"**Step {k}** at {_num(row.get('t'), 1, 's')}: speed {_num(row.get('speed'), 2, 'm/s')}, "
                 f"accel {_num(row.get('accel'), 2, 'm/s²')}, steer rate {_num(row.get('steer_rate'), 3, 'rad/s')} "
                 f"(the controls applied after it); collision {contact}; off-road "
                 f"{'yes' if row.get('offroad') else 'no'}"]
        scored = [f"{name} {_num(row[name], 2)}" for name in STEP_SCORES if isinstance(row.get(name), (int, float))]
        if scored:
            parts.append("Scores of this step: " + ", ".join(scored))
        if self.observed_frame(k) is None:
            parts.append(self.missing_frame_reason(k))
        return "\n\n".join(parts)

    def _check(self, frame: int) -> int:
        if not 0 <= int(frame) < self.n_frames:
            raise OmniscsError(f"step {frame} is out of range: the run has steps 0 to {self.n_frames - 1}")
        return int(frame)


#: Per-step scores of steps.json shown while scrubbing, in this order.
STEP_SCORES = ("pdms", "nc", "dac", "ttc", "comfort", "ep", "epdms", "ddc", "tlc", "lk", "hc", "ec", "hd_step", "rc")
#: The sub-scores of each headline score in run.json's "scores" ("<name>_mean" / "<name>_min"); EPDMS's lie in
#: its own "epdms_scores".
PDMS_PARTS = (("NC", "nc"), ("DAC", "dac"), ("TTC", "ttc"), ("C", "comfort"), ("EP", "ep"))
EPDMS_PARTS = (("NC", "nc"), ("DAC", "dac"), ("DDC", "ddc"), ("TLC", "tlc"), ("EP", "ep"), ("TTC", "ttc"),
               ("LK", "lk"), ("HC", "hc"), ("EC", "ec"))
HD_PARTS = (("NC", "hd_nc"), ("DAC", "hd_dac"), ("TTC", "hd_ttc"), ("C", "hd_comfort"))


def scores_markdown(scores: dict) -> str:
    """run.json's scores as a Markdown table: PDMS, EPDMS and HD-Score with their sub-scores (mean and worst
    step), then route completion."""
    epdms = scores.get("epdms_scores") if isinstance(scores.get("epdms_scores"), dict) else {}
    rows = ["| score | value | sub-scores (mean / min) |", "|---|---|---|"]
    for title, value, parts, source in (("PDMS", scores.get("pdms"), PDMS_PARTS, scores),
                                        ("EPDMS", scores.get("epdms"), EPDMS_PARTS, epdms),
                                        ("HD-Score", scores.get("hd_score"), HD_PARTS, scores)):
        subs = [f"{label} {_num(source.get(f'{key}_mean'), 2)} / {_num(source.get(f'{key}_min'), 2)}"
                for label, key in parts if f"{key}_mean" in source]
        rows.append(f"| {title} | {_num(value, 3)} | {', '.join(subs) or 'n/a'} |")
    rows.append(f"| RC | {_num(scores.get('route_completion'), 3)} | route completion |")
    return "\n".join(rows)


def _num(value, digits: int, unit: str = "") -> str:
    """``value`` with ``digits`` decimals (and its ``unit``), or "n/a" when it is no finite number."""
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(float(value)):
        return "n/a"
    return f"{float(value):.{digits}f}" + (f" {unit}" if unit else "")


def notice_image(text: str, size: tuple[int, int] = NOTICE_SIZE) -> np.ndarray:  # -> uint8 [H, W, 3]
    """A dark picture saying ``text`` (wrapped), for the camera panel when there is no frame to show."""
    import textwrap

    from PIL import Image, ImageDraw

    picture = Image.new("RGB", size, (40, 40, 40))
    draw = ImageDraw.Draw(picture)
    for i, line in enumerate(textwrap.wrap(text, width=max(10, size[0] // 7))):
        draw.text((12, 12 + 16 * i), line, fill=(230, 230, 230))
    return np.asarray(picture, dtype=np.uint8)


def is_run_folder(path: Path) -> bool:
    from omniscs.closedloop.run import RUN_JSON

    return path.is_dir() and (path / RUN_JSON).is_file()
