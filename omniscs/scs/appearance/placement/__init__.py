"""Where an inserted object may go: the checks a placement (x, y, yaw of the object's box, world frame) must pass,
and a sampler that draws N valid placements for 1-to-N generation.

A placement must keep its footprint on the drivable area (``on_road``), stay clear of every logged agent, static
object and the ego at every frame both exist (``no_overlap``), be seen by the chosen camera in enough frames
(``visible``) and lie at the requested distance from it (``in_range``). All checks are geometry on boxes (numpy),
not renders: they are cheap enough to run on thousands of proposals. The object is static (one pose in every
frame) or follows given per-frame poses (e.g. it replaces a logged agent and inherits its motion).

The checks live in ``checks`` (with what they read of a scene in ``context`` and the settings in ``config``), the
sampler in ``sampler``; this module gathers their public names.
"""
from __future__ import annotations

from omniscs.scs.appearance.placement.checks import (ObjectPoses, PlacementCheck, TOUCH_TOLERANCE_M, Visibility,
                                                     boxes_overlap, camera_distances, check_placement, in_range,
                                                     no_overlap, on_road, on_road_frames, overlap_pairs, require_valid,
                                                     segment_hits_box, visibility, visible)
from omniscs.scs.appearance.placement.config import (CHECKS, EGO_HEIGHT_M, EGO_TRACK_ID, OVERLAPS_ACCEPTED,
                                                     PROPOSAL_BATCH, PlacementConfig, YAW_MODES)
from omniscs.scs.appearance.placement.context import (Cameras, GroundHeight, LaneDirection, Obstacles, PlacementContext,
                                                      placement_context)
from omniscs.scs.appearance.placement.sampler import PlacementError, PlacementResult, sample_placements

__all__ = ["CHECKS", "Cameras", "EGO_HEIGHT_M", "EGO_TRACK_ID", "GroundHeight", "LaneDirection", "OVERLAPS_ACCEPTED",
           "ObjectPoses", "Obstacles", "PROPOSAL_BATCH", "PlacementCheck", "PlacementConfig", "PlacementContext",
           "PlacementError", "PlacementResult", "TOUCH_TOLERANCE_M", "Visibility", "YAW_MODES", "boxes_overlap",
           "camera_distances", "check_placement", "in_range", "no_overlap", "on_road", "on_road_frames",
           "overlap_pairs", "placement_context", "require_valid", "sample_placements", "segment_hits_box", "visibility",
           "visible"]
