"""Render + annotate: every variant rendered through its fitted scene graph, with ground truth made automatically
(3D/2D boxes, instance masks, depth, visibility, LiDAR points, velocities, the ego's command), written as scene
stores; and the datasets assembled from them (card, preview, catalog rows)."""
from omniscs.annotate.config import AnnotateConfig

__all__ = ["AnnotateConfig"]
