"""Procedural driving world: layouts, assets, traffic, ray-cast rendering with exact ground truth, edits."""
from omniscs.world.assets import Asset, asset_category, build_asset, list_asset_ids
from omniscs.world.edit import apply_edits
from omniscs.world.layouts import TEMPLATES, Layout, Lane, build_layout, layout_for, road_map_for
from omniscs.world.model import LAYOUT_VERSION, AgentTrack, CameraSpec, LidarSpec, World
from omniscs.world.render import CameraRender, WorldRenderer
from omniscs.world.traffic import LIGHTINGS, camera_rig, generate_world

__all__ = [
    "World", "AgentTrack", "CameraSpec", "LidarSpec", "LAYOUT_VERSION",
    "generate_world", "camera_rig", "WorldRenderer", "CameraRender", "apply_edits",
    "list_asset_ids", "build_asset", "asset_category", "Asset",
    "TEMPLATES", "LIGHTINGS", "Layout", "Lane", "build_layout", "layout_for", "road_map_for",
]
