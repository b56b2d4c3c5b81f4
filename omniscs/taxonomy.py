"""The project's one object taxonomy (nuScenes detection classes plus debris) and semantic classes."""
from __future__ import annotations

#: Object categories every source maps to; readers keep the source label beside it.
CATEGORIES: tuple[str, ...] = (
    "car", "truck", "bus", "trailer", "construction_vehicle", "pedestrian",
    "motorcycle", "bicycle", "traffic_cone", "barrier", "debris",
)

#: Categories that are vehicles (they can move, drive lanes, and get 360° models).
VEHICLE_CATEGORIES: frozenset[str] = frozenset(
    {"car", "truck", "bus", "trailer", "construction_vehicle", "motorcycle", "bicycle"}
)

#: Semantic-mask class ids written by the synthetic world (uint8 per pixel).
SEMANTIC_CLASSES: dict[int, str] = {
    0: "sky",
    1: "road",
    2: "lane_marking",
    3: "sidewalk",
    4: "kerb",
    5: "building",
    6: "pole",
    7: "vegetation",
    8: "vehicle",
    9: "obstacle",
    10: "terrain",
}
SEMANTIC_IDS: dict[str, int] = {name: i for i, name in SEMANTIC_CLASSES.items()}

#: nuScenes category -> nuScenes detection class (the devkit's ``category_to_detection_name``, which mmdet3d's
#: ``NuScenesDataset.NameMapping`` repeats).
NUSCENES_DETECTION_CLASS: dict[str, str] = {
    "movable_object.barrier": "barrier", "vehicle.bicycle": "bicycle", "vehicle.bus.bendy": "bus",
    "vehicle.bus.rigid": "bus", "vehicle.car": "car", "vehicle.construction": "construction_vehicle",
    "vehicle.motorcycle": "motorcycle", "human.pedestrian.adult": "pedestrian", "human.pedestrian.child": "pedestrian",
    "human.pedestrian.construction_worker": "pedestrian", "human.pedestrian.police_officer": "pedestrian",
    "movable_object.trafficcone": "traffic_cone", "vehicle.trailer": "trailer", "vehicle.truck": "truck",
}
