"""One closed-loop run from start to end: reset, ask the policy, step, until the episode ends; then its scores, a
bird's-eye replay picture, a contact sheet of rendered frames and an animated GIF, written as one run folder, with
what a replay of its steps needs (``omniscs view RUN``): the agents' boxes and the camera frame of every step."""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from omniscs.closedloop import metrics
from omniscs.closedloop.epdms import EPDMSConfig, score_with_epdms
from omniscs.closedloop.scenario import ClosedLoopScenario
from omniscs.closedloop.simulator import EGO_HEIGHT_M, Simulator, agent_heights
from omniscs.errors import ValidationError
from omniscs.progress import Progress, no_progress
from omniscs.scs.behavior.collision import footprints
from omniscs.storage import atomic_directory, atomic_write_json

log = logging.getLogger(__name__)

RUN_JSON = "run.json"
STEPS_JSON = "steps.json"
BEV_PNG = "bev.png"
FRAMES_PNG = "frames.png"
REPLAY_GIF = "replay.gif"
#: What a step-by-step replay reads (``replay_record``), and the folder of the camera frames the policy saw.
REPLAY_JSON = "replay.json"
FRAMES_DIR = "frames"
#: Layout version of replay.json (bump when it changes).
REPLAY_VERSION = 1
#: The frames of FRAMES_DIR: JPEG of this quality, at the run's size or this width when the run's is wider
#: (measured: 15 KB a frame of the test graph rendered at 640x360, 22 KB a procedural world's 480x270 camera image:
#: 1 to 2 MB for a 60-step run, less than its replay.gif).
FRAME_MAX_WIDTH = 640
FRAME_QUALITY = 85
#: Decimals of the positions (0.1 mm) and angles of replay.json: exact enough to draw, a third of the bytes.
REPLAY_DECIMALS = 4
#: Rendered frames kept for the contact sheet and the GIF (evenly spaced), and the GIF's width in pixels.
SHEET_FRAMES = 8
GIF_WIDTH = 320
GIF_MAX_FRAMES = 100
#: The bird's-eye picture shows this much around the ego's and the reference's paths (metres).
BEV_MARGIN_M = 20.0


@dataclass(frozen=True)
class RunResult:
    folder: Path | None
    summary: dict       # run.json's content
    scores: "metrics.RunScores"
    trace: "metrics.RunTrace | None" = None  # what was scored (to score it again, e.g. with another EPDMS config)


def run_episode(sim: Simulator, policy, scenario: ClosedLoopScenario, max_steps: int | None = None,
                out_dir: str | Path | None = None, camera: str | None = None, overwrite: bool = False,
                progress: Progress = no_progress, epdms: "EPDMSConfig | None" = None) -> RunResult:
    """Drive ``scenario`` with ``policy`` for at most ``max_steps`` steps (default: until it ends) and score it
    (PDMS, HD-Score, and EPDMS with ``epdms``, default ``EPDMSConfig()``); with ``out_dir``, write run.json,
    steps.json and the pictures there (atomically). ``camera`` is the one shown in the pictures (default: the rig's
    first)."""
    if max_steps is not None and max_steps < 1:
        raise ValidationError(f"max_steps must be >= 1 (got {max_steps})")
    started = time.perf_counter()
    res = sim.reset(scenario)
    policy.reset(sim)
    camera = camera or sim.rig[0].name
    limit = scenario.n_steps - 1 if max_steps is None else max_steps
    frames = [(0, res.observation.rgb.get(camera))]
    policy_s = 0.0
    reason = None
    for k in range(limit):
        tick = time.perf_counter()
        action = policy.act(sim)
        policy_s += time.perf_counter() - tick
        res = sim.step(action)
        frames.append((k + 1, res.observation.rgb.get(camera)))
        progress(k + 1, limit, f"{scenario.scenario_id}: rc {res.info['rc']:.2f}")
        if res.done:
            reason = res.reason
            break
    if reason is None:
        sim.stop("max_steps")
    trace = scored_trace(sim)
    scores = score_with_epdms(trace, config=epdms)
    summary = run_summary(sim, scores, getattr(policy, "name", type(policy).__name__),
                          time.perf_counter() - started, policy_s)
    folder = None
    if out_dir is not None:
        folder = write_run(sim, scores, summary, frames, Path(out_dir), overwrite, camera)
    return RunResult(folder, summary, scores, trace)


def scored_trace(sim: Simulator) -> "metrics.RunTrace":
    """The simulator's trace with what EPDMS reads from the scenario: for a log scenario, the logged ego and agents
    (the human-agent filter); the lane centrelines of the scenario's road map (None when its map was derived from
    the log's tracks: no lane map). A behaviour variant gets no filter: its world was never driven by a human (NAVSIM
    filters its original scenes only, never its synthetic ones)."""
    trace = sim.trace()
    sc = sim.episode.scenario
    lanes = getattr(getattr(sc.drivable, "road_map", None), "lane_centrelines", None)
    lanes = tuple(lanes) if lanes else None
    if sc.kind != "log":
        return replace(trace, lane_centrelines=lanes)
    at = np.minimum(np.arange(trace.steps), sc.n_steps - 1)  # step k of the run is step k of the scenario
    return replace(trace, reference_ego=sc.ego[at], reference_agents=sc.agents[:, at], lane_centrelines=lanes)


def run_summary(sim: Simulator, scores: "metrics.RunScores", policy: str, seconds: float, policy_s: float = 0.0
                ) -> dict:
    """run.json's content for the simulator's (ended) episode: what ran, why it ended, its scores and timing."""
    ep = sim.episode
    sc = ep.scenario
    timing = dict(ep.timing.as_dict(), policy_s=policy_s)
    busy = timing["render_s"] + timing["controller_s"] + timing["world_s"] + policy_s
    return {
        "scenario_id": sc.scenario_id, "scene_id": sc.scene_id, "kind": sc.kind, "policy": policy,
        "steps": ep.step, "dt": sc.dt, "simulated_s": round(ep.step * sc.dt, 6), "reason": ep.reason,
        "reactive": sim.config.reactive, "cameras": [c.name for c in sim.rig],
        "size": [sim.rig[0].width, sim.rig[0].height], "scores": scores.to_dict(), "seconds": seconds,
        "steps_per_s": ep.step / max(busy, 1e-9), "timing": timing,
        "collided_with": sorted({int(sc.track_ids[c.track]) for cs in ep.contacts for c in cs}),
        "adversary": sc.adversary,
    }


def step_rows(sim: Simulator, scores: "metrics.RunScores") -> list[dict]:
    """Per step: time, ego pose and motion, applied controls, contact, off-road and the step's scores."""
    ep = sim.episode
    per = scores.to_dict().get("per_step", {})
    rows = []
    for k in range(len(ep.ego)):
        x, y, yaw = (float(v) for v in ep.ego[k])
        ctrl = ep.controls[k]
        row = {"step": k, "t": round(k * ep.scenario.dt, 6), "x": x, "y": y, "yaw": yaw, "speed": float(ep.speed[k]),
               "accel": None if ctrl is None else float(ctrl[0]), "steer_rate": None if ctrl is None else float(ctrl[1]),
               "collision": bool(ep.contacts[k]), "offroad": bool(ep.offroad[k])}
        for name, values in per.items():
            if k < len(values):
                row[name] = values[k]
        rows.append(row)
    return rows


def write_run(sim: Simulator, scores, summary: dict, frames: list, out_dir: Path, overwrite: bool,
              camera: str | None = None) -> Path:
    """The run folder: run.json, steps.json, the pictures, and replay.json with the frames of ``frames`` ([(step,
    uint8 [H, W, 3] or None)], the rig's camera ``camera``, default its first) under FRAMES_DIR."""
    with atomic_directory(out_dir, overwrite=overwrite) as tmp:
        atomic_write_json(tmp / RUN_JSON, summary)
        (tmp / STEPS_JSON).write_text(json.dumps(step_rows(sim, scores), allow_nan=False))
        bev_picture(sim, summary, tmp / BEV_PNG)
        shown = [(k, f) for k, f in frames if f is not None]
        if shown:
            contact_sheet(shown, sim.episode.scenario.dt, tmp / FRAMES_PNG)
            replay_gif(shown, sim.episode.scenario.dt, tmp / REPLAY_GIF)
        kept, size = observed_frames(shown, tmp / FRAMES_DIR)
        (tmp / REPLAY_JSON).write_text(json.dumps(replay_record(sim, camera or sim.rig[0].name, kept, size),
                                                  allow_nan=False))
    return out_dir


def observed_frames(frames: list, folder: Path) -> tuple[dict[int, str], tuple[int, int] | None]:
    """Each (step, uint8 [H, W, 3]) of ``frames`` as a JPEG in ``folder`` (at most FRAME_MAX_WIDTH wide); returns
    {step: its path relative to the run folder} and the JPEGs' (width, height) (None without frames)."""
    from PIL import Image

    out, size = {}, None
    for k, img in frames:
        h, w = img.shape[:2]
        picture = Image.fromarray(img)
        if w > FRAME_MAX_WIDTH:
            picture = picture.resize((FRAME_MAX_WIDTH, max(2, int(round(h * FRAME_MAX_WIDTH / w)))), Image.BILINEAR)
        folder.mkdir(exist_ok=True)
        name = f"{int(k):06d}.jpg"
        picture.save(folder / name, quality=FRAME_QUALITY)
        out[int(k)] = f"{folder.name}/{name}"
        size = picture.size
    return out, size


def replay_record(sim: Simulator, camera: str, frame_files: dict[int, str], frame_size: tuple[int, int] | None
                  ) -> dict:
    """replay.json's content: per step the boxes of the agents present (row into ``tracks``, x, y, z, yaw: world
    box centres, metres and radians), the ego's ground height, the track ids the ego touched and its camera frame's
    file (``frame_files``, None where none was kept; ``frame_size``: their width and height); once, the tracks
    (id, category, size), the ego's box, the rig as rendered, the scenario's reference ego path and its road map
    (None when it has none)."""
    ep = sim.episode
    sc = ep.scenario
    d = REPLAY_DECIMALS
    ego = np.array(ep.ego)  # [T, 3]
    # the height world_from_ego gives each step: the reference's at its position nearest the ego
    nearest = np.argmin(np.linalg.norm(sc.ego[None, :, :2] - ego[:, None, :2], axis=2), axis=1)
    agents = []
    for k, poses in enumerate(ep.agents):
        z = agent_heights(sc, k)
        z = np.where(np.isfinite(z), z, 0.5 * sc.sizes[:, 2])
        agents.append([[int(i), round(float(poses[i, 0]), d), round(float(poses[i, 1]), d), round(float(z[i]), d),
                        round(float(poses[i, 2]), d)] for i in np.flatnonzero(np.isfinite(poses).all(1))])
    road = getattr(sc.drivable, "road_map", None)
    return {
        "version": REPLAY_VERSION, "dt": sc.dt, "camera": camera,
        "frame_size": None if frame_size is None else [int(frame_size[0]), int(frame_size[1])],
        "frames": [frame_files.get(k) for k in range(len(ego))],
        "ego": {"length": sc.ego_length, "width": sc.ego_width, "height": EGO_HEIGHT_M,
                "centre_ahead_m": sc.ego_centre_ahead_m,
                "ground_z": [round(float(z), d) for z in sc.ego_z[nearest]]},
        "tracks": [{"track_id": int(t), "category": c, "size": [float(v) for v in sc.sizes[i]]}
                   for i, (t, c) in enumerate(zip(sc.track_ids, sc.categories))],
        "agents": agents,
        "contacts": [[int(sc.track_ids[c.track]) for c in cs] for cs in ep.contacts],
        "rig": [{"name": c.name, "width": int(c.width), "height": int(c.height),
                 "K": np.asarray(c.K, np.float64).tolist(),
                 "ego_from_camera": np.asarray(c.ego_from_camera, np.float64).tolist()} for c in sim.rig],
        "reference": np.round(sc.ego, d).tolist(),
        "road": None if road is None else road.to_dict(),
    }


def bev_picture(sim: Simulator, summary: dict, out_png: Path) -> Path:
    """Bird's-eye view of the run: drivable area, the reference path, the ego's path coloured by time with its
    footprint every 0.5 s, the agents' paths, and where contacts happened."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon


    ep = sim.episode
    sc = ep.scenario
    ego = np.array(ep.ego)
    agents = np.stack(ep.agents, 1) if len(sc.track_ids) else np.zeros((0, len(ego), 3))
    pts = np.concatenate([ego[:, :2], sc.ego[:, :2]])
    lo, hi = pts.min(0) - BEV_MARGIN_M, pts.max(0) + BEV_MARGIN_M
    fig, ax = plt.subplots(figsize=(10, max(3.0, 10 * (hi[1] - lo[1]) / max(hi[0] - lo[0], 1e-6))), dpi=80)
    if sc.drivable is not None:
        xs, ys = np.linspace(lo[0], hi[0], 240), np.linspace(lo[1], hi[1], 120)
        gx, gy = np.meshgrid(xs, ys)
        d = np.asarray(sc.drivable.is_drivable(np.stack([gx.ravel(), gy.ravel()], 1))).reshape(gx.shape)
        ax.imshow(d, origin="lower", extent=(lo[0], hi[0], lo[1], hi[1]), cmap="Greys", alpha=0.25, vmin=0, vmax=1.5)
    ax.plot(sc.ego[:, 0], sc.ego[:, 1], "--", color="0.4", lw=1, label="reference")
    every = max(1, int(round(0.5 / sc.dt)))
    for i in range(len(sc.track_ids)):
        a = agents[i]
        ok = np.isfinite(a).all(-1)
        if not ok.any():
            continue
        hit = sc.adversary is not None and int(sc.track_ids[i]) == sc.adversary
        ax.plot(a[ok, 0], a[ok, 1], color="tab:red" if hit else "tab:blue", lw=1, alpha=0.7)
        k = int(np.flatnonzero(ok)[-1])
        ax.add_patch(Polygon(footprints(a[k, :2], a[k, 2], sc.sizes[i, 0], sc.sizes[i, 1]), closed=True,
                             fill=False, ec="tab:red" if hit else "tab:blue", lw=1))
    colours = plt.cm.viridis(np.linspace(0, 1, len(ego)))
    for k in range(0, len(ego), every):
        ax.add_patch(Polygon(footprints(ego[k, :2], ego[k, 2], sc.ego_length, sc.ego_width), closed=True,
                             fill=False, ec=colours[k], lw=1))
    ax.scatter(ego[:, 0], ego[:, 1], c=np.arange(len(ego)) * sc.dt, cmap="viridis", s=6, label="ego")
    hits = [k for k, cs in enumerate(ep.contacts) if cs]
    if hits:
        ax.scatter(ego[hits, 0], ego[hits, 1], marker="x", color="red", s=80, label="contact")
    s = summary["scores"]
    ax.set_title(f"{sc.scenario_id} | {summary['policy']} | {summary['reason']} after {summary['simulated_s']:.1f} s | "
                 f"PDMS {_fmt(s.get('pdms'))} EPDMS {_fmt(s.get('epdms'))} HD-Score {_fmt(s.get('hd_score'))} "
                 f"RC {_fmt(s.get('route_completion'))}",
                 fontsize=9)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(out_png)
    plt.close(fig)
    return out_png


def _fmt(v) -> str:
    return "n/a" if v is None else f"{float(v):.2f}"


def _pick(frames: list, n: int) -> list:
    idx = np.unique(np.linspace(0, len(frames) - 1, min(n, len(frames))).round().astype(int))
    return [frames[i] for i in idx]


def contact_sheet(frames: list, dt: float, out_png: Path) -> Path:
    """Evenly spaced rendered frames in a 4-wide grid, each labelled with its time."""
    from PIL import Image, ImageDraw

    chosen = _pick(frames, SHEET_FRAMES)
    h, w = chosen[0][1].shape[:2]
    scale = min(1.0, 320 / w)
    tw, th = int(w * scale), int(h * scale)
    cols = min(4, len(chosen))
    rows = (len(chosen) + cols - 1) // cols
    sheet = Image.new("RGB", (cols * tw, rows * th), (0, 0, 0))
    for i, (k, img) in enumerate(chosen):
        tile = Image.fromarray(img).resize((tw, th), Image.BILINEAR)
        ImageDraw.Draw(tile).text((4, 4), f"t = {k * dt:.1f} s", fill=(255, 255, 0))
        sheet.paste(tile, ((i % cols) * tw, (i // cols) * th))
    sheet.save(out_png, optimize=True)
    return out_png


def replay_gif(frames: list, dt: float, out_gif: Path) -> Path:
    """The rendered frames as an animated GIF at real time (every frame up to 10 per second)."""
    from PIL import Image

    stride = max(1, int(round(0.1 / dt)), -(-len(frames) // GIF_MAX_FRAMES))
    h, w = frames[0][1].shape[:2]
    size = (GIF_WIDTH, max(2, int(round(h * GIF_WIDTH / w))))
    images = [Image.fromarray(f).resize(size, Image.BILINEAR) for _, f in frames[::stride]]
    images[0].save(out_gif, save_all=True, append_images=images[1:], duration=int(1000 * dt * stride), loop=0)
    return out_gif
