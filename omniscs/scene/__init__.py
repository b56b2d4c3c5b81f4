"""Scene store: load, validate and write driving logs in the project's canonical form."""
from omniscs.scene.store import (
    BOX_COLUMNS,
    SCHEMA_VERSION,
    CameraRecord,
    Scene,
    load_scene,
)
from omniscs.scene.writer import SceneWriter, boxes_frame

__all__ = ["BOX_COLUMNS", "SCHEMA_VERSION", "CameraRecord", "Scene", "SceneWriter", "boxes_frame", "load_scene"]
from omniscs.scene.ingest import StoreSource, check_synthetic, parse_source, source_from_dict, write_source_scene
from omniscs.scene.sources.common import DatasetSource
from omniscs.scene.synthetic import SyntheticSource, write_synthetic_scene, write_world_scene

__all__ += ["DatasetSource", "StoreSource", "SyntheticSource", "check_synthetic", "parse_source", "source_from_dict",
            "write_source_scene", "write_synthetic_scene", "write_world_scene"]
