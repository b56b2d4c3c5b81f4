"""Pictures of a scene: a contact sheet of cameras over time with projected 3D boxes, and a BEV plot."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from omniscs.geometry import (BOX_EDGES, box_corners_from_pose, clip_segment_to_near, invert_transform, make_transform,
                              transform_points)
from omniscs.quaternions import quat_to_rotmat
from omniscs.scene.store import Scene
from omniscs.storage import atomic_write_bytes, atomic_write_with

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
    img = scene.image(cam, frame_idx) if image is None else image
    boxes = [(box_pose(row), (row.length, row.width, row.height), f"{row.category} {row.track_id}",
              track_colour(row.track_id)) for row in scene.boxes_at(frame_idx).itertuples()]
    return draw_box_wireframes(img, scene.intrinsics(cam), invert_transform(scene.world_from_camera(cam, frame_idx)),
                               boxes)


def draw_box_wireframes(image: np.ndarray,            # uint8 [H, W, 3] RGB
                        K: np.ndarray,                # [3, 3]
                        cam_from_world: np.ndarray,   # [4, 4] (OpenCV camera)
                        boxes,  # iterable of (world_from_box [4, 4], size (l, w, h), label, RGB colour)
                        ) -> np.ndarray:              # a copy of ``image`` with the boxes drawn
    """Each box projected as a wireframe (edges clipped at the near plane and to the image), labelled at its top."""
    img = image.copy()
    h, w = img.shape[:2]
    thickness = max(1, w // 320)
    for world_from_box, size, label, colour in boxes:
        corners = transform_points(cam_from_world, box_corners_from_pose(world_from_box, size))
        if np.all(corners[:, 2] <= 0):
            continue
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
            cv2.putText(img, label, (max(0, x), max(10, y - 3)), cv2.FONT_HERSHEY_SIMPLEX, 0.35, colour, 1,
                        cv2.LINE_AA)
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


#: Metres around the ego path that a BEV plot shows; agents wholly outside are left out.
BEV_MARGIN_M = 35.0
#: Width of a BEV figure in inches; its height follows the region's aspect within these bounds.
BEV_WIDTH_IN, BEV_MIN_HEIGHT_IN, BEV_MAX_HEIGHT_IN = 11.0, 4.0, 11.0


def bev_plot(scene: Scene, out_png: Path) -> Path:
    """Bird's-eye view around the ego path: map (for synthetic scenes), ego path and every nearby
    track with box footprints at its first and last frame. Written atomically."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ego = scene.world_from_ego_all[:, :3, 3]
    lo, hi = ego[:, :2].min(0) - BEV_MARGIN_M, ego[:, :2].max(0) + BEV_MARGIN_M
    span = hi - lo
    height_in = float(np.clip(BEV_WIDTH_IN * span[1] / span[0], BEV_MIN_HEIGHT_IN, BEV_MAX_HEIGHT_IN))
    fig, ax = plt.subplots(figsize=(BEV_WIDTH_IN, height_in), dpi=110)
    world = scene.world
    if world is not None:
        from omniscs.world import layout_for

        layout = layout_for(world)
        for poly in layout.sidewalk_polygons:
            ax.fill(poly[:, 0], poly[:, 1], color="0.85", zorder=0, lw=0)
        for poly in layout.drivable_polygons:
            ax.fill(poly[:, 0], poly[:, 1], color="0.65", zorder=0, lw=0)
    ax.plot(ego[:, 0], ego[:, 1], "-", color="black", lw=2.5, label="ego path", zorder=4)
    ax.plot(*ego[0, :2], "o", color="black", zorder=4)
    shown = 0
    for track_id, g in scene.boxes.groupby("track_id"):
        g = g.sort_values("frame_idx")
        xy = g[["cx", "cy"]].to_numpy()
        if not np.any(np.all((xy >= lo) & (xy <= hi), axis=1)):
            continue
        shown += 1
        colour = np.array(track_colour(track_id)) / 255.0
        ax.plot(xy[:, 0], xy[:, 1], "-", color=colour, lw=1.5, zorder=3)
        for k, row in enumerate((g.iloc[0], g.iloc[-1])):
            corners = box_corners_from_pose(box_pose(row), [row.length, row.width, row.height])
            foot = corners[[0, 2, 6, 4, 0], :2]  # outline of the face at +z
            ax.fill(foot[:, 0], foot[:, 1], color=colour, alpha=0.25 if k == 0 else 0.6, zorder=3)
            ax.plot(foot[:, 0], foot[:, 1], color=colour, lw=0.8, zorder=3)
        last = g.iloc[-1]
        ax.annotate(str(track_id), (last.cx, last.cy), fontsize=7, ha="center", va="center", zorder=5)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, world)")
    ax.set_ylabel("y (m, world)")
    ax.set_title(f"{scene.scene_id}: {shown} of {scene.boxes.track_id.nunique()} tracks near the ego path, "
                 f"{scene.n_frames} frames (faint box = first frame, solid = last)", fontsize=9)
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    try:
        return atomic_write_with(out_png, lambda buf: fig.savefig(buf, format="png"))
    finally:
        plt.close(fig)


def write_previews(scene: Scene, out_dir: Path) -> dict[str, Path]:
    """Both pictures under ``out_dir``: contact_sheet.png and bev.png."""
    out_dir = Path(out_dir)
    return {"contact_sheet": contact_sheet(scene, out_dir / "contact_sheet.png"),
            "bev": bev_plot(scene, out_dir / "bev.png")}
