"""Scene-graph checkpoints: tensors in safetensors, plus JSON with the plan, config, scene content hash and version."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from omniscs.checks import is_int, read_json
from omniscs.errors import OmniscsError
from omniscs.gaussians import PARAM_NAMES, GaussianParams
from omniscs.nsg.agent import AgentNode
from omniscs.devices import resolve_device
from omniscs.nsg.graph import BACKGROUND, RenderSettings, SceneGraph, agent_key
from omniscs.nsg.relight import LIGHTING_ROWS, RELIGHT_TENSORS, Relight
from omniscs.nsg.sky import SkyParams
from omniscs.plan import ScenePlan
from omniscs.render.sh import MAX_SH_DEGREE
from omniscs.scene.store import CameraRecord
from omniscs.storage import atomic_directory, atomic_write_json, file_sha256

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
        if a.relight is not None:
            for name in RELIGHT_TENSORS:  # saved as agent.<id>.relight.<name>
                tensors[f"{key}.relight.{name}"] = getattr(a.relight, name)
    tensors["sky.texture"] = graph.sky.texture
    for cam, affine in graph.exposure.items():
        tensors[f"exposure.{cam}"] = affine
    tensors["world_from_ego"] = torch.from_numpy(np.array(graph.world_from_ego))
    # clones: an edited graph may share one tensor between nodes, which safetensors refuses
    return {k: v.detach().clone().contiguous() for k, v in tensors.items()}


def save_checkpoint(graph: SceneGraph, out_dir: str | Path, plan: ScenePlan | None = None,
                    config: dict | None = None, metrics: dict | None = None, overwrite: bool = False) -> Path:
    """Write ``graph`` (and what made it) to ``out_dir`` atomically: the folder appears whole or not at all. The
    JSON records the tensor file's size and sha256, so a damaged or truncated checkpoint is refused on load."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not overwrite:
        raise OmniscsError(f"{out_dir} already exists; choose another checkpoint folder or overwrite it")
    with atomic_directory(out_dir, overwrite=overwrite) as tmp:
        write_checkpoint_files(graph, tmp, plan, config, metrics)
    return out_dir


def write_checkpoint_files(graph: SceneGraph, folder: Path, plan: ScenePlan | None = None, config: dict | None = None,
                           metrics: dict | None = None) -> None:
    """The checkpoint's files written into ``folder`` (a temporary folder its caller renames into place whole)."""
    meta = {
        "kind": KIND, "version": CHECKPOINT_VERSION, "scene_id": graph.scene_id, "content_hash": graph.content_hash,
        "sh_degree": graph.sh_degree, "settings": graph.settings.__dict__,
        "cameras": [{"name": c.name, "width": c.width, "height": c.height, "K": c.K.tolist(),
                     "ego_from_camera": c.ego_from_camera.tolist()} for c in graph.cameras],
        "agents": [{"track_id": a.track_id, "category": a.category, "n_gaussians": len(a.gaussians),
                    **({"relight": True} if a.relight is not None else {})} for a in graph.agents],
        "exposure_cameras": list(graph.exposure), "n_gaussians": graph.n_gaussians, "config": config,
    }
    save_file(_graph_tensors(graph), str(folder / TENSORS))
    meta[TENSORS_RECORD] = {"bytes": (folder / TENSORS).stat().st_size, "sha256": file_sha256(folder / TENSORS)}
    atomic_write_json(folder / GRAPH_JSON, meta)
    if plan is not None:
        (folder / PLAN_JSON).write_text(plan.to_json() + "\n")
    if metrics is not None:
        atomic_write_json(folder / METRICS_JSON, metrics)


#: graph.json field with the tensor file's size and sha256 (checkpoints written before it lack it).
TENSORS_RECORD = "tensors"
_AGAIN = "the checkpoint is damaged: fit the scene again (omniscs fit)"


def _is_matrix(v, n: int) -> bool:
    try:
        m = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        return False
    return isinstance(v, list) and m.shape == (n, n) and bool(np.all(np.isfinite(m)))


def _check_meta(path: Path, meta: dict) -> None:
    """Every field ``load_graph`` uses is there with the right type; else one OmniscsError naming it."""
    def bad(field: str, what: str):
        value = repr(meta.get(field) if "." not in field else "...")
        raise OmniscsError(f"{path}: field {field} must be {what}; got {value[:60]} ({_AGAIN})")

    required = {"scene_id": str, "content_hash": str, "sh_degree": int, "settings": dict, "cameras": list,
                "agents": list, "exposure_cameras": list}
    missing = [k for k in required if k not in meta]
    if missing:
        raise OmniscsError(f"{path}: missing field(s) {missing}; {_AGAIN}")
    for key, kind in required.items():
        if not (is_int(meta[key]) if kind is int else isinstance(meta[key], kind)):
            bad(key, f"a JSON {'integer' if kind is int else kind.__name__.replace('dict', 'object')}")
    if not 0 <= meta["sh_degree"] <= MAX_SH_DEGREE:  # a degree the renderer cannot draw is refused on reading
        bad("sh_degree", f"0..{MAX_SH_DEGREE}")
    known = {f.name for f in dataclasses.fields(RenderSettings)}
    if set(meta["settings"]) - known:
        bad("settings", f"an object with fields among {sorted(known)}")
    for i, c in enumerate(meta["cameras"]):
        if not (isinstance(c, dict) and isinstance(c.get("name"), str) and is_int(c.get("width"))
                and is_int(c.get("height")) and c["width"] > 0 and c["height"] > 0 and _is_matrix(c.get("K"), 3)
                and _is_matrix(c.get("ego_from_camera"), 4)):
            bad(f"cameras.{i}", "a camera: name, positive width and height, K (3x3), ego_from_camera (4x4)")
    for i, a in enumerate(meta["agents"]):
        if not (isinstance(a, dict) and is_int(a.get("track_id")) and a["track_id"] >= 0
                and isinstance(a.get("category"), str)):
            bad(f"agents.{i}", "an agent: non-negative integer track_id and a category")
        if not isinstance(a.get("relight", False), bool):
            bad(f"agents.{i}.relight", "true or false")
    if not all(isinstance(c, str) for c in meta["exposure_cameras"]):
        bad("exposure_cameras", "a list of camera names")
    record = meta.get(TENSORS_RECORD)
    if record is not None and not (isinstance(record, dict) and is_int(record.get("bytes"))
                                   and isinstance(record.get("sha256"), str)):
        bad(TENSORS_RECORD, "an object with bytes and sha256")


def read_checkpoint_meta(ckpt_dir: str | Path) -> dict:
    """The checkpoint's JSON description, after checking its kind, version and fields."""
    path = Path(ckpt_dir) / GRAPH_JSON
    if not path.is_file():
        raise OmniscsError(f"{ckpt_dir} is not a scene-graph checkpoint (no {GRAPH_JSON}); fit one with omniscs fit")
    meta = read_json(path, _AGAIN)
    if not isinstance(meta, dict):
        raise OmniscsError(f"{path} must be a JSON object; got a {type(meta).__name__} ({_AGAIN})")
    if meta.get("kind") != KIND:
        raise OmniscsError(f"{ckpt_dir} holds a {meta.get('kind')!r} checkpoint, not a scene graph")
    if meta.get("version") != CHECKPOINT_VERSION:
        raise OmniscsError(f"{ckpt_dir} is a version {meta.get('version')} scene-graph checkpoint; this omniscs reads "
                           f"version {CHECKPOINT_VERSION}: fit the scene again")
    _check_meta(path, meta)
    return meta


def _load_tensors(ckpt_dir: Path, meta: dict) -> dict[str, torch.Tensor]:
    path = ckpt_dir / TENSORS
    if not path.is_file():
        raise OmniscsError(f"{path} is missing; the checkpoint is incomplete, fit again")
    record = meta.get(TENSORS_RECORD)
    if record is not None:
        size = path.stat().st_size
        if size != record["bytes"]:
            raise OmniscsError(f"{path} is {size} bytes but {GRAPH_JSON} records {record['bytes']} (truncated); "
                               f"{_AGAIN}")
        if file_sha256(path) != record["sha256"]:
            raise OmniscsError(f"{path} does not match the sha256 in {GRAPH_JSON}; {_AGAIN}")
    try:
        return load_file(str(path))
    except Exception as exc:  # safetensors raises its own error type (and OSError) for damaged files
        detail = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:200]
        raise OmniscsError(f"{path} is not a readable safetensors file ({detail}); {_AGAIN}") from None


def _tensor(t: dict, path: Path, key: str, shape: tuple, floating: bool = True) -> torch.Tensor:
    """``t[key]`` when its shape matches ``shape`` (None: any size) and its dtype kind; else one OmniscsError."""
    if key not in t:
        raise OmniscsError(f"{path} has no tensor {key!r}; {_AGAIN}")
    x = t[key]
    ok = x.dim() == len(shape) and all(want is None or got == want for got, want in zip(x.shape, shape))
    if not ok or x.dtype.is_floating_point != floating:
        want = "x".join("N" if d is None else str(d) for d in shape)
        raise OmniscsError(f"{path}: tensor {key!r} is {x.dtype} {list(x.shape)}, expected "
                           f"{'float' if floating else 'integer'} [{want}]; {_AGAIN}")
    return x


def load_graph(ckpt_dir: str | Path, scene=None, device: torch.device | str = "cpu") -> SceneGraph:
    """The graph saved in ``ckpt_dir`` with its tensors on ``device`` (wherever it was fitted); with ``scene``,
    refuse a checkpoint fitted to other scene content. A damaged, truncated or incomplete checkpoint is one
    OmniscsError."""
    device = resolve_device(device)
    ckpt_dir = Path(ckpt_dir)
    meta = read_checkpoint_meta(ckpt_dir)
    if scene is not None:
        check_same_scene(meta, scene, ckpt_dir)
    t = _load_tensors(ckpt_dir, meta)
    path = ckpt_dir / TENSORS

    def params(prefix: str) -> GaussianParams:
        n = _tensor(t, path, f"{prefix}.means", (None, 3)).shape[0]
        shapes = {"means": (n, 3), "quats": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,), "sh_dc": (n, 3),
                  "sh_rest": (n, None, 3)}
        return GaussianParams(**{name: _tensor(t, path, f"{prefix}.{name}", shapes[name]) for name in PARAM_NAMES})

    world_from_ego = _tensor(t, path, "world_from_ego", (None, 4, 4)).numpy().copy()
    n_frames = world_from_ego.shape[0]
    if n_frames == 0 or not np.all(np.isfinite(world_from_ego)):
        raise OmniscsError(f"{path}: tensor 'world_from_ego' has no frames or NaN/Inf values; {_AGAIN}")
    agents = []
    for a in meta["agents"]:
        key = agent_key(a["track_id"])
        present = _tensor(t, path, f"{key}.present", (n_frames,), floating=False)
        gaussians = params(key)
        relight = None
        if a.get("relight"):
            n = len(gaussians)
            old = t.get(f"{key}.relight.lighting")
            if old is not None and tuple(old.shape) == (5, 3) and f"{key}.relight.specular" not in t:
                raise OmniscsError(f"{path}: agent {a['track_id']} was relit by an earlier light model (5 lighting "
                                   "rows, no materials): fit the scene again (omniscs fit)")
            relight = Relight(*(_tensor(t, path, f"{key}.relight.{name}", shape) for name, shape in (
                ("albedo", (n, 3)), ("normals", (n, 3)), ("specular", (n,)), ("shininess", (n,)),
                ("lighting", (LIGHTING_ROWS, 3)))))
        agents.append(AgentNode(int(a["track_id"]), a["category"], _tensor(t, path, f"{key}.size", (3,)).numpy().copy(),
                                _tensor(t, path, f"{key}.world_from_agent", (n_frames, 4, 4)).numpy().copy(),
                                present.numpy().astype(bool), gaussians, relight))
    cameras = tuple(CameraRecord(c["name"], int(c["width"]), int(c["height"]), np.array(c["K"], dtype=np.float64),
                                 np.array(c["ego_from_camera"], dtype=np.float64)) for c in meta["cameras"])
    exposure = {c: _tensor(t, path, f"exposure.{c}", (3, 4)) for c in meta["exposure_cameras"]}
    graph = SceneGraph(meta["scene_id"], meta["content_hash"], params(BACKGROUND), tuple(agents),
                       SkyParams(_tensor(t, path, "sky.texture", (3, None, None))), exposure, cameras,
                       world_from_ego, int(meta["sh_degree"]), RenderSettings(**meta["settings"]))
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
    if not path.is_file():
        return None
    d = read_json(path, _AGAIN)
    if not isinstance(d, dict):
        raise OmniscsError(f"{path} must be a JSON object; got a {type(d).__name__} ({_AGAIN})")
    try:
        return ScenePlan.from_dict(d)
    except OmniscsError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        detail = (str(exc).strip().splitlines() or [""])[0][:200]
        raise OmniscsError(f"{path} is not a scene plan ({type(exc).__name__}: {detail}); {_AGAIN}") from None


def load_metrics(ckpt_dir: str | Path) -> dict:
    path = Path(ckpt_dir) / METRICS_JSON
    if not path.is_file():
        return {}
    d = read_json(path, _AGAIN)
    if not isinstance(d, dict):
        raise OmniscsError(f"{path} must be a JSON object; got a {type(d).__name__} ({_AGAIN})")
    return d
