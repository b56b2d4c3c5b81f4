"""Neural scene graph of Gaussians: a background node, agent nodes posed per frame (Eq. 1), a sky; fitted
to a driving log, edited as values, saved as checkpoints."""
from omniscs.nsg.agent import AgentNode
from omniscs.nsg.checkpoint import CHECKPOINT_VERSION, load_graph, save_checkpoint
from omniscs.nsg.config import PRESETS, FitConfig, InitConfig, LearningRates, LossConfig, fit_preset
from omniscs.nsg.edit import apply_graph_edits
from omniscs.nsg.graph import RenderOutput, RenderSettings, SceneGraph, render_view
from omniscs.nsg.observations import Observations, View
from omniscs.nsg.strategy import DensifyStrategy
from omniscs.nsg.train import FitDiverged, FitResult, evaluate_graph, fit_scene

__all__ = [
    "AgentNode", "CHECKPOINT_VERSION", "load_graph", "save_checkpoint", "apply_graph_edits", "PRESETS",
    "FitConfig", "InitConfig", "LearningRates", "LossConfig", "fit_preset",
    "RenderOutput", "RenderSettings", "SceneGraph", "render_view", "Observations", "View", "DensifyStrategy",
    "FitDiverged", "FitResult", "evaluate_graph", "fit_scene",
]
