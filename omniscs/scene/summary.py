"""Summaries of a scene for the catalog: one row per scene, per agent track and per frame."""
from __future__ import annotations

import json

import numpy as np

from omniscs.geometry import yaw_from_matrix
from omniscs.scene.store import Scene

#: A track whose box centre travels further than this over the log counts as moving (metres).
MOVING_PATH_LENGTH_M = 1.0


def agent_rows(scene: Scene) -> list[dict]:
    """Per track: size, lifetime, path length, top speed, moving or static, visibility statistics."""
    rows = []
    ts = scene.frames["timestamp_us"].to_numpy() * 1e-6
    ego_xy = scene.world_from_ego_all[:, :2, 3]
    for track_id, g in scene.boxes.groupby("track_id", sort=True):
        g = g.sort_values("frame_idx")
        frames = g["frame_idx"].to_numpy()
        xyz = g[["cx", "cy", "cz"]].to_numpy()
        steps = np.linalg.norm(np.diff(xyz[:, :2], axis=0), axis=1)
        dt = np.diff(ts[frames])
        speeds = steps / np.maximum(dt, 1e-6) if len(steps) else np.zeros(0)
        path = float(steps.sum())
        vis = g["visible_pixels"].to_numpy()
        known_vis = bool(np.all(vis >= 0))
        pts = g["num_lidar_points"].to_numpy()
        dist = np.linalg.norm(xyz[:, :2] - ego_xy[frames], axis=1)
        rows.append({
            "scene_id": scene.scene_id, "track_id": int(track_id), "category": str(g["category"].iloc[0]),
            "source_category": g["source_category"].iloc[0],
            "length": float(g["length"].median()), "width": float(g["width"].median()),
            "height": float(g["height"].median()),
            "first_frame": int(frames[0]), "last_frame": int(frames[-1]), "n_frames": len(frames),
            "path_length_m": path, "max_speed_mps": float(speeds.max()) if len(speeds) else 0.0,
            "moving": path > MOVING_PATH_LENGTH_M,
            "frames_visible": int((vis > 0).sum()) if known_vis else None,
            "mean_visible_pixels": float(vis.mean()) if known_vis else None,
            "max_visible_pixels": int(vis.max()) if known_vis else None,
            "mean_lidar_points": float(pts.mean()) if np.all(pts >= 0) else None,
            "min_distance_to_ego_m": float(dist.min()),
        })
    return rows


def frame_rows(scene: Scene) -> list[dict]:
    """Per frame: timestamp, ego pose and speed, how many boxes and visible agents."""
    poses = scene.world_from_ego_all
    ts = scene.frames["timestamp_us"].to_numpy()
    xy = poses[:, :2, 3]
    speed = np.zeros(len(ts))
    if len(ts) > 1:
        v = np.linalg.norm(np.diff(xy, axis=0), axis=1) / (np.diff(ts) * 1e-6)
        speed[1:] = v
        speed[0] = v[0]
    counts = scene.boxes.groupby("frame_idx").size()
    visible = scene.boxes[scene.boxes.visible_pixels > 0].groupby("frame_idx").size()
    known_vis = bool(len(scene.boxes) == 0 or (scene.boxes.visible_pixels >= 0).all())
    yaw = yaw_from_matrix(poses[:, :3, :3])
    return [{
        "scene_id": scene.scene_id, "frame_idx": int(f), "timestamp_us": int(ts[f]),
        "ego_x": float(poses[f, 0, 3]), "ego_y": float(poses[f, 1, 3]), "ego_z": float(poses[f, 2, 3]),
        "ego_yaw": float(yaw[f]), "ego_speed_mps": float(speed[f]),
        "n_boxes": int(counts.get(f, 0)),
        "n_visible_agents": int(visible.get(f, 0)) if known_vis else None,
    } for f in range(scene.n_frames)]


def scene_row(scene: Scene, agents: list[dict], reused: bool, ingest_seconds: float,
              preview_path: str | None = None) -> dict:
    """The scene's catalog row; ``agents`` are its ``agent_rows``."""
    src = scene.source
    ts = scene.frames["timestamp_us"].to_numpy()
    return {
        "scene_id": scene.scene_id, "source_kind": src.get("kind", "unknown"),
        "source_json": json.dumps(src, sort_keys=True),
        "template": scene.manifest.get("template"), "lighting": scene.manifest.get("lighting"),
        "seed": scene.manifest.get("seed"),
        "source_scene_id": scene.manifest.get("source_scene_id"), "dataroot": src.get("dataroot"),
        "location": scene.manifest.get("location"),
        "path": str(scene.path), "content_hash": scene.content_hash, "n_frames": scene.n_frames,
        "duration_s": float((ts[-1] - ts[0]) * 1e-6), "cameras": scene.camera_names,
        "n_tracks": len(agents), "n_moving": sum(a["moving"] for a in agents),
        "has_lidar": scene.has_lidar, "has_gt": scene.has_gt, "reused": reused,
        "ingest_seconds": float(ingest_seconds), "preview_path": preview_path,
    }
