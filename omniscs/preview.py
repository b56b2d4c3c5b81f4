"""Pictures of a scene: a contact sheet of cameras over time with projected 3D boxes, and a BEV plot."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from omniscs.geometry import (BOX_EDGES, box_corners_from_pose, clip_segment_to_near, invert_transform,
                              make_transform, quat_to_rotmat, transform_points)
from omniscs.scene.store import Scene
from omniscs.storage import atomic_write_bytes

#: Rows (time steps) shown in a contact sheet.
CONTACT_SHEET_ROWS = 4
#: Widest camera tile in a contact sheet; larger images are scaled down.
MAX_TILE_WIDTH = 480
#: Order of nuScenes camera names from left to right, so a sheet reads like the view around the car.
CAMERA_ORDER = ("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT")


def track_colour(track_id: int) -> tuple[int, int, int]:
    """A stable, saturated RGB colour per track id."""
    hue = (int(track_id) * 0.618033988749895) % 1.0
    hsv = np.uint8([[[int(hue * 179), 220, 255]]])
    return tuple(int(c) for c in cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0])


def ordered_cameras(names: list[str]) -> list[str]:
    rank = {n: i for i, n in enumerate(CAMERA_ORDER)}
    return sorted(names, key=lambda n: (rank.get(n, len(rank)), n))


def box_pose(row) -> np.ndarray:  # -> [4, 4] world_from_box
    return make_transform(quat_to_rotmat(np.array([row.qw, row.qx, row.qy, row.qz])), [row.cx, row.cy, row.cz])


def draw_boxes(scene: Scene, cam: str, frame_idx: int, image: np.ndarray | None = None) -> np.ndarray:
    """The camera image with every box of the frame drawn as a projected wireframe, labelled."""
    img = (scene.image(cam, frame_idx) if image is None else image).copy()
    K = scene.intrinsics(cam)
    cam_from_world = invert_transform(scene.world_from_camera(cam, frame_idx))
    h, w = img.shape[:2]
    thickness = max(1, w // 320)
    for row in scene.boxes_at(frame_idx).itertuples():
        corners = transform_points(cam_from_world, box_corners_from_pose(box_pose(row), [row.length, row.width, row.height]))
        if np.all(corners[:, 2] <= 0):
            continue
        colour = track_colour(row.track_id)
        drawn = []
        for i, j in BOX_EDGES:
            seg = clip_segment_to_near(corners[i], corners[j], near=0.1)
            if seg is None:
                continue
            (u0, v0), (u1, v1) = [(p[:2] / p[2]) @ K[:2, :2].T + K[:2, 2] for p in seg]
            pts = np.clip(np.array([u0, v0, u1, v1]), -4 * max(w, h), 4 * max(w, h))
            ok, p0, p1 = cv2.clipLine((0, 0, w, h), (int(pts[0]), int(pts[1])), (int(pts[2]), int(pts[3])))
            if ok:
                cv2.line(img, p0, p1, colour, thickness, cv2.LINE_AA)
                drawn.append(p0)
        if drawn:
            x, y = min(drawn, key=lambda p: p[1])
            cv2.putText(img, f"{row.category} {row.track_id}", (max(0, x), max(10, y - 3)),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.35, colour, 1, cv2.LINE_AA)
    return img


def contact_sheet(scene: Scene, out_png: Path, rows: int = CONTACT_SHEET_ROWS) -> Path:
    """Cameras side by side (left to right) over evenly spaced frames, boxes drawn; written atomically."""
    frames = np.unique(np.linspace(0, scene.n_frames - 1, min(rows, scene.n_frames)).round().astype(int))
    cams = ordered_cameras(scene.camera_names)
    tile_w = min(MAX_TILE_WIDTH, max(scene.image_size(c)[0] for c in cams))
    tile_h = max(int(round(scene.image_size(c)[1] * tile_w / scene.image_size(c)[0])) for c in cams)
    sheet_rows = []
    for f in frames:
        tiles = []
        for c in cams:
            tile = cv2.resize(draw_boxes(scene, c, int(f)), (tile_w, tile_h), interpolation=cv2.INTER_AREA)
            cv2.putText(tile, f"{c}  frame {f}", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1,
                        cv2.LINE_AA)
            tiles.append(tile)
        sheet_rows.append(np.concatenate(tiles, axis=1))
    sheet = np.concatenate(sheet_rows, axis=0)
    ok, png = cv2.imencode(".png", cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    return atomic_write_bytes(out_png, png.tobytes())


def bev_plot(scene: Scene, out_png: Path) -> Path:
    """Bird's-eye view of the ego path and every track, with box footprints at first and last frame."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 8), dpi=110)
    ego = scene.world_from_ego_all[:, :3, 3]
    ax.plot(ego[:, 0], ego[:, 1], "-", color="black", lw=2.5, label="ego", zorder=3)
    ax.annotate("ego start", ego[0, :2], fontsize=8)
    for track_id, g in scene.boxes.groupby("track_id"):
        g = g.sort_values("frame_idx")
        colour = np.array(track_colour(track_id)) / 255.0
        ax.plot(g.cx, g.cy, "-", color=colour, lw=1.5, zorder=2)
        for row in (g.iloc[0], g.iloc[-1]):
            corners = box_corners_from_pose(box_pose(row), [row.length, row.width, row.height])
            foot = corners[[0, 2, 6, 4, 0], :2]  # outline of the face at +z
            ax.fill(foot[:, 0], foot[:, 1], color=colour, alpha=0.35, zorder=2)
            ax.plot(foot[:, 0], foot[:, 1], color=colour, lw=0.8)
        first = g.iloc[0]
        ax.annotate(f"{first.category} {track_id}", (first.cx, first.cy), fontsize=7, color=colour * 0.7)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, world)")
    ax.set_ylabel("y (m, world)")
    ax.set_title(f"{scene.scene_id}: {scene.boxes.track_id.nunique()} tracks, {scene.n_frames} frames")
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    tmp = Path(out_png).with_suffix(".tmp.png")
    Path(out_png).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(tmp)
    plt.close(fig)
    tmp.replace(out_png)
    return Path(out_png)


def write_previews(scene: Scene, out_dir: Path) -> dict[str, Path]:
    """Both pictures under ``out_dir``: contact_sheet.png and bev.png."""
    out_dir = Path(out_dir)
    return {"contact_sheet": contact_sheet(scene, out_dir / "contact_sheet.png"),
            "bev": bev_plot(scene, out_dir / "bev.png")}
