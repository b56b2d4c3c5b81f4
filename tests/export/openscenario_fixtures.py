"""Small variant stores of one procedural intersection for the OpenSCENARIO export tests: a behaviour variant (one
agent cut sideways) and an appearance variant (an overturned truck inserted), written as the annotate stage writes
variant stores (frames, procedural world, boxes, variant.json) with flat thumbnail images: about a second."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd

from omniscs.geometry import rotmat_from_euler, yaw_from_matrix
from omniscs.quaternions import rotmat_to_quat
from omniscs.scene import SceneWriter, SyntheticSource, load_scene, write_synthetic_scene

#: A 4-way intersection (junction paths, both arms), six frames, one thumbnail camera: renders in about a second.
SOURCE = SyntheticSource(template="intersection", seed=1, n_frames=6, n_cameras=1, width=32, height=18)
#: The track id of the object the appearance variant inserts.
INSERTED_TRACK = 900


def variant_store(scene, out: Path, store_id: str, boxes: pd.DataFrame, variant: dict | None,
                  world: bool = True) -> Path:
    """A variant store of ``scene``: its frames, camera and procedural world, the given boxes, ``variant`` as its
    variant.json (as the annotate stage writes it), flat images."""
    camera = scene.camera(scene.camera_names[0])
    with SceneWriter(out, store_id, {"kind": "variant", "scene_id": scene.scene_id}) as writer:
        writer.set_frames(scene.frames["timestamp_us"].to_numpy(np.int64), scene.world_from_ego_all)
        writer.set_cameras([camera])
        writer.set_boxes(boxes)
        writer.set_extra(source_scene_id=scene.scene_id)
        if world:
            writer.write_world_json((scene.path / "world.json").read_text())
        for f in range(scene.n_frames):
            writer.write_image(camera.name, f, np.full((camera.height, camera.width, 3), 90, np.uint8))
        if variant is not None:
            (writer.tmp / "variant.json").write_text(json.dumps({"variant": variant}))
    return out


def adversarial_boxes(scene, track: int, metres_per_frame: float) -> pd.DataFrame:
    """The log's boxes with ``track`` drifting sideways (to its left) by ``metres_per_frame`` every frame."""
    boxes = scene.boxes.copy()
    rows = boxes.track_id == track
    yaw = boxes.loc[rows, "yaw"].to_numpy()
    step = boxes.loc[rows, "frame_idx"].to_numpy() * metres_per_frame
    boxes.loc[rows, "cx"] -= np.sin(yaw) * step
    boxes.loc[rows, "cy"] += np.cos(yaw) * step
    return boxes


def inserted_boxes(scene) -> pd.DataFrame:
    """The log's boxes plus an overturned truck standing still 25 m ahead of the first ego pose."""
    pose = scene.world_from_ego(0)
    yaw = float(yaw_from_matrix(pose[:3, :3])) + 0.4
    q = rotmat_to_quat(rotmat_from_euler(math.pi, 0.0, yaw))
    centre = pose[:3, 3] + pose[:3, 0] * 25.0 + np.array([0.0, 0.0, 1.4])
    rows = [dict(frame_idx=f, track_id=INSERTED_TRACK, category="truck", source_category="truck", cx=centre[0],
                 cy=centre[1], cz=centre[2], length=8.0, width=2.5, height=2.8, yaw=yaw, qw=q[0], qx=q[1], qy=q[2],
                 qz=q[3], num_lidar_points=-1, visible_pixels=-1) for f in range(scene.n_frames)]
    return pd.concat([scene.boxes, pd.DataFrame(rows)], ignore_index=True)


def moving_track(scene) -> int:
    """A track that moves (the adversary of the behaviour variant)."""
    speed = scene.boxes.groupby("track_id").apply(lambda g: np.ptp(g.cx.to_numpy()) + np.ptp(g.cy.to_numpy()))
    return int(speed.idxmax())


_CACHE: dict[str, object] = {}


def source_scene(tmp_path_factory):
    """The intersection log, rendered once per test process."""
    if "scene" not in _CACHE:
        _CACHE["scene"] = load_scene(write_synthetic_scene(SOURCE, tmp_path_factory.mktemp("xosc-source") / "store"))
    return _CACHE["scene"]


def variant_stores(tmp_path_factory) -> list[Path]:
    """A behaviour variant (one agent cut sideways) and an appearance variant (an overturned truck inserted), in one
    variants folder (``<folder>/scenes/<store id>``), written once per test process."""
    if "variants" not in _CACHE:
        scene = source_scene(tmp_path_factory)
        root = tmp_path_factory.mktemp("xosc-variants")
        adversary = moving_track(scene)
        behaviour = variant_store(scene, root / "scenes" / "beh-v000", "beh-v000",
                                  adversarial_boxes(scene, adversary, 0.1),
                                  {"variant_id": "v000", "scene_id": scene.scene_id, "adversary": adversary})
        appearance = variant_store(scene, root / "scenes" / "app-v000", "app-v000", inserted_boxes(scene),
                                   {"variant_id": "a000", "scene_id": scene.scene_id, "kind": "appearance",
                                    "placement": "insert", "track_id": INSERTED_TRACK, "adversary": INSERTED_TRACK,
                                    "pose": {"static": True, "roll_deg": 180.0}})
        _CACHE["variants"] = [behaviour, appearance]
    return _CACHE["variants"]
