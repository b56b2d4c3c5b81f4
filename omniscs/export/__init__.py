"""Writers of scene stores as nuScenes v1.0 (with map expansions), UniAD training data, KITTI tracking, Waymo Open
Dataset v2 datasets and OpenSCENARIO scenarios on OpenDRIVE road networks."""
from __future__ import annotations

from omniscs.export.common import export_scenes
from omniscs.export.kitti import write_kitti
from omniscs.export.nuscenes import write_nuscenes
from omniscs.export.openscenario import write_openscenario
from omniscs.export.uniad import write_uniad
from omniscs.export.waymo_v2 import write_waymo_v2

#: Export format name -> writer(scenes, root, progress=None, **options).
WRITERS = {"nuscenes": write_nuscenes, "uniad": write_uniad, "kitti": write_kitti, "waymo-v2": write_waymo_v2,
           "openscenario": write_openscenario}

__all__ = ["WRITERS", "export_scenes", "write_kitti", "write_nuscenes", "write_openscenario", "write_uniad",
           "write_waymo_v2"]
