"""Scene-graph checkpoints: tensors in safetensors, plus JSON with the plan, config, scene content hash and version."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from omniscs.errors import OmniscsError
from omniscs.gaussians import PARAM_NAMES, GaussianParams
from omniscs.nsg.agent import AgentNode
from omniscs.devices import resolve_device
from omniscs.nsg.graph import BACKGROUND, RenderSettings, SceneGraph, agent_key
from omniscs.nsg.sky import SkyParams
from omniscs.plan import ScenePlan
from omniscs.scene.store import CameraRecord
from omniscs.storage import atomic_directory, atomic_write_json

#: Bump when the checkpoint layout or the meaning of a stored tensor changes; older ones are refused.
CHECKPOINT_VERSION = 1

#: What a checkpoint folder holds.
GRAPH_JSON = "graph.json"
TENSORS = "gaussians.safetensors"
PLAN_JSON = "plan.json"
METRICS_JSON = "metrics.json"
KIND = "omniscs-nsg"


def _graph_tensors(graph: SceneGraph) -> dict[str, torch.Tensor]:
    tensors: dict[str, torch.Tensor] = {}
    for name in PARAM_NAMES:
        tensors[f"{BACKGROUND}.{name}"] = getattr(graph.background, name)
    for a in graph.agents:
        key = agent_key(a.track_id)
        for name in PARAM_NAMES:
            tensors[f"{key}.{name}"] = getattr(a.gaussians, name)
        tensors[f"{key}.world_from_agent"] = torch.from_numpy(np.array(a.world_from_agent))
        tensors[f"{key}.present"] = torch.from_numpy(a.present.astype(np.uint8))
        tensors[f"{key}.size"] = torch.from_numpy(np.array(a.size))
    tensors["sky.texture"] = graph.sky.texture
    for cam, affine in graph.exposure.items():
        tensors[f"exposure.{cam}"] = affine
    tensors["world_from_ego"] = torch.from_numpy(np.array(graph.world_from_ego))
    # clones: an edited graph may share one tensor between nodes, which safetensors refuses
    return {k: v.detach().clone().contiguous() for k, v in tensors.items()}


def save_checkpoint(graph: SceneGraph, out_dir: str | Path, plan: ScenePlan | None = None,
                    config: dict | None = None, metrics: dict | None = None, overwrite: bool = False) -> Path:
    """Write ``graph`` (and what made it) to ``out_dir`` atomically: the folder appears whole or not at all."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not overwrite:
        raise OmniscsError(f"{out_dir} already exists; choose another checkpoint folder or overwrite it")
    meta = {
        "kind": KIND, "version": CHECKPOINT_VERSION, "scene_id": graph.scene_id, "content_hash": graph.content_hash,
        "sh_degree": graph.sh_degree, "settings": graph.settings.__dict__,
        "cameras": [{"name": c.name, "width": c.width, "height": c.height, "K": c.K.tolist(),
                     "ego_from_camera": c.ego_from_camera.tolist()} for c in graph.cameras],
        "agents": [{"track_id": a.track_id, "category": a.category, "n_gaussians": len(a.gaussians)}
                   for a in graph.agents],
        "exposure_cameras": list(graph.exposure), "n_gaussians": graph.n_gaussians, "config": config,
    }
    with atomic_directory(out_dir, overwrite=overwrite) as tmp:
        save_file(_graph_tensors(graph), str(tmp / TENSORS))
        atomic_write_json(tmp / GRAPH_JSON, meta)
        if plan is not None:
            (tmp / PLAN_JSON).write_text(plan.to_json() + "\n")
        if metrics is not None:
            atomic_write_json(tmp / METRICS_JSON, metrics)
    return out_dir


def read_checkpoint_meta(ckpt_dir: str | Path) -> dict:
    """The checkpoint's JSON description, after checking its kind and version."""
    path = Path(ckpt_dir) / GRAPH_JSON
    if not path.is_file():
        raise OmniscsError(f"{ckpt_dir} is not a scene-graph checkpoint (no {GRAPH_JSON}); fit one with omniscs fit")
    try:
        meta = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise OmniscsError(f"{path} is not valid JSON ({exc}); the checkpoint is damaged, fit again") from None
    if meta.get("kind") != KIND:
        raise OmniscsError(f"{ckpt_dir} holds a {meta.get('kind')!r} checkpoint, not a scene graph")
    if meta.get("version") != CHECKPOINT_VERSION:
        raise OmniscsError(f"{ckpt_dir} is a version {meta.get('version')} scene-graph checkpoint; this omniscs reads "
                           f"version {CHECKPOINT_VERSION}: fit the scene again")
    return meta


def load_checkpoint(ckpt_dir: str | Path, scene=None, device: torch.device | str = "cpu") -> SceneGraph:
    """The graph saved in ``ckpt_dir`` with its tensors on ``device`` (wherever it was fitted); with ``scene``,
    refuse a checkpoint fitted to other scene content."""
    device = resolve_device(device)
    meta = read_checkpoint_meta(ckpt_dir)
    if scene is not None:
        check_same_scene(meta, scene, ckpt_dir)
    tensors_path = Path(ckpt_dir) / TENSORS
    if not tensors_path.is_file():
        raise OmniscsError(f"{tensors_path} is missing; the checkpoint is incomplete, fit again")
    t = load_file(str(tensors_path))

    def params(prefix: str) -> GaussianParams:
        return GaussianParams(**{name: t[f"{prefix}.{name}"] for name in PARAM_NAMES})

    agents = []
    for a in meta["agents"]:
        key = agent_key(a["track_id"])
        agents.append(AgentNode(int(a["track_id"]), a["category"], t[f"{key}.size"].numpy().copy(),
                                t[f"{key}.world_from_agent"].numpy().copy(), t[f"{key}.present"].numpy().astype(bool),
                                params(key)))
    cameras = tuple(CameraRecord(c["name"], int(c["width"]), int(c["height"]), np.array(c["K"], dtype=np.float64),
                                 np.array(c["ego_from_camera"], dtype=np.float64)) for c in meta["cameras"])
    graph = SceneGraph(meta["scene_id"], meta["content_hash"], params(BACKGROUND), tuple(agents),
                       SkyParams(t["sky.texture"]), {c: t[f"exposure.{c}"] for c in meta["exposure_cameras"]},
                       cameras, t["world_from_ego"].numpy().copy(), int(meta["sh_degree"]),
                       RenderSettings(**meta["settings"]))
    return graph.to(device)  # poses and sizes stay numpy on the host; only the tensors move


def check_same_scene(meta_or_graph, scene, ckpt_dir: str | Path | None = None) -> None:
    """Raise unless the checkpoint (or graph) was fitted to exactly this scene's content."""
    content = meta_or_graph["content_hash"] if isinstance(meta_or_graph, dict) else meta_or_graph.content_hash
    scene_id = meta_or_graph["scene_id"] if isinstance(meta_or_graph, dict) else meta_or_graph.scene_id
    if content != scene.content_hash:
        where = f"{ckpt_dir} was" if ckpt_dir is not None else "the scene graph was"
        raise OmniscsError(f"{where} fitted to scene {scene_id} (content {content[:12]}), not to {scene.scene_id} "
                           f"(content {scene.content_hash[:12]}); use that scene's checkpoint or fit this one")


def load_plan(ckpt_dir: str | Path) -> ScenePlan | None:
    path = Path(ckpt_dir) / PLAN_JSON
    return ScenePlan.from_dict(json.loads(path.read_text())) if path.is_file() else None


def load_metrics(ckpt_dir: str | Path) -> dict:
    path = Path(ckpt_dir) / METRICS_JSON
    return json.loads(path.read_text()) if path.is_file() else {}
