"""Damaged scene-graph checkpoints: every truncated, changed, incomplete or mistyped checkpoint is one OmniscsError
line (never a safetensors, KeyError or TypeError traceback), and nothing is written while refusing it. The graph is
made by hand (a few hundred Gaussians), so no fit is needed."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from safetensors.torch import load_file, save_file

from omniscs.errors import OmniscsError
from omniscs.gaussians import GaussianParams
from omniscs.geometry import ego_from_camera_mount, intrinsics_from_fov, pose_from_xyz_yaw
from omniscs.nsg.agent import AgentNode
from omniscs.nsg.checkpoint import (GRAPH_JSON, METRICS_JSON, PLAN_JSON, TENSORS, TENSORS_RECORD, load_graph,
                                    load_metrics, load_plan, read_checkpoint_meta, save_checkpoint)
from omniscs.nsg.graph import RenderSettings, SceneGraph
from omniscs.nsg.sky import SkyParams
from omniscs.scene.store import CameraRecord
from tests.damage import cut, files_under, write

N_FRAMES = 3


def _params(n: int, seed: int, sh_degree: int = 1) -> GaussianParams:
    g = torch.Generator().manual_seed(seed)
    return GaussianParams(means=torch.randn(n, 3, generator=g), quats=torch.randn(n, 4, generator=g),
                          log_scales=torch.randn(n, 3, generator=g) - 2, opacity_logits=torch.randn(n, generator=g),
                          sh_dc=torch.randn(n, 3, generator=g),
                          sh_rest=torch.zeros(n, (sh_degree + 1) ** 2 - 1, 3))


def tiny_graph() -> SceneGraph:
    poses = np.stack([pose_from_xyz_yaw(float(f), 0.0, 0.0, 0.0) for f in range(N_FRAMES)])
    agent = AgentNode(3, "car", np.array([4.5, 1.9, 1.6]),
                      np.stack([pose_from_xyz_yaw(10.0 + f, 0.0, 0.8, 0.0) for f in range(N_FRAMES)]),
                      np.ones(N_FRAMES, dtype=bool), _params(40, 1))
    cam = CameraRecord("CAM_FRONT", 32, 18, intrinsics_from_fov(32, 18, np.radians(70)),
                       ego_from_camera_mount(1.5, 0.0, 1.6, 0.0))
    return SceneGraph("ckpt-test", "0" * 64, _params(200, 0), (agent,), SkyParams(torch.zeros(3, 4, 8)),
                      {"CAM_FRONT": torch.eye(3, 4)}, (cam,), poses, 1, RenderSettings())


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> Path:
    return save_checkpoint(tiny_graph(), tmp_path_factory.mktemp("ckpt") / "ckpt", metrics={"status": "fitted"})


# ----------------------------------------------------------------------------- damage
def meta_change(change):
    def damage(ckpt: Path):
        meta = json.loads((ckpt / GRAPH_JSON).read_text())
        change(meta)
        (ckpt / GRAPH_JSON).write_text(json.dumps(meta))
    return damage


def old_checkpoint(damage=None):
    """As a checkpoint written before the tensor record existed, then ``damage``."""
    def apply(ckpt: Path):
        meta_change(lambda m: m.pop(TENSORS_RECORD))(ckpt)
        if damage is not None:
            damage(ckpt)
    return apply


def flip(name: str, where: float = 0.7):
    def damage(ckpt: Path):
        data = bytearray((ckpt / name).read_bytes())
        data[int(len(data) * where)] ^= 0x55
        (ckpt / name).write_bytes(bytes(data))
    return damage


def tensors(change):
    """Re-save the tensors through ``change(dict)`` (as an old checkpoint: no record to compare with)."""
    def damage(ckpt: Path):
        t = load_file(str(ckpt / TENSORS))
        change(t)
        save_file(t, str(ckpt / TENSORS))
    return old_checkpoint(damage)


CASES = {
    # graph.json
    "graph.json a list": (write(GRAPH_JSON, b"[1, 2, 3]"), r"graph.json must be a JSON object; got a list"),
    "graph.json not JSON": (write(GRAPH_JSON, b"{kind: nsg"), r"graph.json is not valid JSON"),
    "graph.json cut in half": (cut(GRAPH_JSON), r"graph.json is not valid JSON"),
    "graph.json empty": (write(GRAPH_JSON, b""), r"graph.json is not valid JSON"),
    "graph.json binary": (write(GRAPH_JSON, b"\xff\xd8\xff\xe0"), r"graph.json is not UTF-8 text \(byte 0 is 0xff\)"),
    "graph.json nested 100,000 deep": (write(GRAPH_JSON, b"[" * 100_000), r"graph.json is nested more than 256 deep"),
    "graph.json with a 5000-digit number": (write(GRAPH_JSON, b"[" + b"9" * 5000 + b"]"),
                                            r"graph.json holds an integer of 5000 digits"),
    "graph.json missing": (lambda ckpt: (ckpt / GRAPH_JSON).unlink(), r"is not a scene-graph checkpoint \(no graph.json\)"),
    "another kind": (meta_change(lambda m: m.update(kind="omniscs-pool")), r"holds a 'omniscs-pool' checkpoint"),
    "another version": (meta_change(lambda m: m.update(version=7)), r"is a version 7 scene-graph checkpoint"),
    "missing agents field": (meta_change(lambda m: m.pop("agents")), r"graph.json: missing field\(s\) \['agents'\]"),
    "cameras a dict": (meta_change(lambda m: m.update(cameras={})), r"field cameras must be a JSON list"),
    "sh_degree a string": (meta_change(lambda m: m.update(sh_degree="1")), r"field sh_degree must be a JSON integer"),
    "sh_degree huge": (meta_change(lambda m: m.update(sh_degree=40)), r"field sh_degree must be 0..3"),
    "sh_degree beyond the renderer": (meta_change(lambda m: m.update(sh_degree=4)), r"field sh_degree must be 0..3"),
    "unknown render setting": (meta_change(lambda m: m["settings"].update(turbo=True)),
                               r"field settings must be an object with fields among"),
    "camera without K": (meta_change(lambda m: m["cameras"][0].pop("K")), r"field cameras.0 must be a camera"),
    "camera of negative width": (meta_change(lambda m: m["cameras"][0].update(width=-5)),
                                 r"field cameras.0 must be a camera"),
    "agent track id a bool": (meta_change(lambda m: m["agents"][0].update(track_id=True)),
                              r"field agents.0 must be an agent"),
    "agent not an object": (meta_change(lambda m: m.update(agents=[3])), r"field agents.0 must be an agent"),
    "tensor record malformed": (meta_change(lambda m: m.update(tensors="yes")), r"field tensors must be an object"),
    # the tensor file
    "tensors missing": (lambda ckpt: (ckpt / TENSORS).unlink(), r"gaussians.safetensors is missing; the checkpoint is "
                                                                 r"incomplete"),
    "tensors cut in half": (cut(TENSORS), r"gaussians.safetensors is \d+ bytes but graph.json records \d+ \(truncated\)"),
    "tensors byte changed": (flip(TENSORS), r"gaussians.safetensors does not match the sha256 in graph.json"),
    "tensors empty": (write(TENSORS, b""), r"gaussians.safetensors is 0 bytes but graph.json records"),
    "old: tensors cut in half": (old_checkpoint(cut(TENSORS)), r"gaussians.safetensors is not a readable safetensors"),
    "old: tensors garbage": (old_checkpoint(write(TENSORS, b"\x10\x00\x00\x00\x00\x00\x00\x00{not json}")),
                             r"gaussians.safetensors is not a readable safetensors"),
    "old: tensors header damaged": (old_checkpoint(flip(TENSORS, 0.0001)),
                                    r"gaussians.safetensors is not a readable safetensors"),
    "old: tensors a directory": (old_checkpoint(lambda ckpt: ((ckpt / TENSORS).unlink(), (ckpt / TENSORS).mkdir())),
                                 r"gaussians.safetensors is missing"),
    "old: sky tensor missing": (tensors(lambda t: t.pop("sky.texture")), r"has no tensor 'sky.texture'"),
    "old: agent tensor missing": (tensors(lambda t: t.pop("agent.3.present")), r"has no tensor 'agent.3.present'"),
    "old: poses of the wrong shape": (tensors(lambda t: t.update(world_from_ego=torch.zeros(N_FRAMES, 4, 3,
                                                                                            dtype=torch.float64))),
                                      r"tensor 'world_from_ego' is torch.float64 \[3, 4, 3\], expected float \[Nx4x4\]"),
    "old: NaN poses": (tensors(lambda t: t["world_from_ego"].fill_(float("nan"))),
                       r"tensor 'world_from_ego' has no frames or NaN/Inf"),
    "old: means of the wrong width": (tensors(lambda t: t.update({"background.means": torch.zeros(200, 2)})),
                                      r"tensor 'background.means' is torch.float32 \[200, 2\]"),
    "old: opacities of another count": (tensors(lambda t: t.update({"background.opacity_logits": torch.zeros(7)})),
                                        r"tensor 'background.opacity_logits' is torch.float32 \[7\], expected float \[200\]"),
    "old: presence of another length": (tensors(lambda t: t.update({"agent.3.present": torch.ones(9, dtype=torch.uint8)})),
                                        r"tensor 'agent.3.present' is torch.uint8 \[9\], expected integer \[3\]"),
    "old: exposure missing": (tensors(lambda t: t.pop("exposure.CAM_FRONT")), r"has no tensor 'exposure.CAM_FRONT'"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_damaged_checkpoint_is_one_domain_error_line(case, pristine, tmp_path):
    ckpt = Path(shutil.copytree(pristine, tmp_path / "ckpt"))
    damage, message = CASES[case]
    damage(ckpt)
    before = files_under(tmp_path)
    with pytest.raises(OmniscsError, match=message) as info:
        load_graph(ckpt)
    assert len(str(info.value).splitlines()) == 1
    assert files_under(tmp_path) == before


SIDE_CASES = {
    "plan.json not JSON": (write(PLAN_JSON, b"{"), load_plan, r"plan.json is not valid JSON"),
    "plan.json a list": (write(PLAN_JSON, b"[]"), load_plan, r"plan.json must be a JSON object; got a list"),
    "plan.json of another version": (write(PLAN_JSON, b'{"version": 0}'), load_plan, r"plan version 0 is not"),
    "plan.json without fields": (lambda ckpt: (ckpt / PLAN_JSON).write_text(json.dumps({"version": _plan_version()})),
                                 load_plan, r"plan.json is not a scene plan \(KeyError"),
    "metrics.json cut": (cut(METRICS_JSON), load_metrics, r"metrics.json is not valid JSON"),
    "metrics.json a number": (write(METRICS_JSON, b"3"), load_metrics, r"metrics.json must be a JSON object"),
    "not a checkpoint folder": (lambda ckpt: shutil.rmtree(ckpt) or ckpt.mkdir(), read_checkpoint_meta,
                                r"is not a scene-graph checkpoint \(no graph.json\); fit one"),
    "a file, not a folder": (lambda ckpt: shutil.rmtree(ckpt) or ckpt.write_text("x"), load_graph,
                             r"is not a scene-graph checkpoint"),
}


def _plan_version() -> int:
    from omniscs.plan import PLAN_VERSION

    return PLAN_VERSION


@pytest.mark.parametrize("case", list(SIDE_CASES))
def test_a_damaged_plan_metrics_or_folder_is_one_domain_error_line(case, pristine, tmp_path):
    ckpt = Path(shutil.copytree(pristine, tmp_path / "ckpt"))
    damage, read, message = SIDE_CASES[case]
    damage(ckpt)
    before = files_under(tmp_path)
    with pytest.raises(OmniscsError, match=message) as info:
        read(ckpt)
    assert len(str(info.value).splitlines()) == 1
    assert files_under(tmp_path) == before


def test_a_good_checkpoint_loads_with_its_record_and_without_it(pristine, tmp_path):
    graph = load_graph(pristine)
    assert graph.agent_ids == (3,) and graph.n_gaussians == 240 and graph.n_frames == N_FRAMES
    record = json.loads((pristine / GRAPH_JSON).read_text())[TENSORS_RECORD]
    assert record["bytes"] == (pristine / TENSORS).stat().st_size and len(record["sha256"]) == 64
    old = Path(shutil.copytree(pristine, tmp_path / "old"))
    old_checkpoint()(old)  # checkpoints written before the record existed stay readable
    assert torch.equal(load_graph(old).background.means, graph.background.means)
    assert load_metrics(pristine) == {"status": "fitted"} and load_plan(tmp_path) is None


@pytest.fixture(scope="module")
def tensor_bytes(pristine) -> bytes:
    return (pristine / TENSORS).read_bytes()


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(fraction=st.floats(0.0, 0.999), keep_record=st.booleans())
def test_any_truncation_of_the_tensors_is_one_domain_error(pristine, tensor_bytes, tmp_path_factory, fraction,
                                                           keep_record):
    """Property: cutting the tensor file anywhere (with or without the recorded size and hash) is refused with one
    OmniscsError line, never another exception."""
    ckpt = Path(shutil.copytree(pristine, tmp_path_factory.mktemp("cut") / "ckpt"))
    if not keep_record:
        old_checkpoint()(ckpt)
    (ckpt / TENSORS).write_bytes(tensor_bytes[: int(len(tensor_bytes) * fraction)])
    with pytest.raises(OmniscsError) as info:
        load_graph(ckpt)
    assert len(str(info.value).splitlines()) == 1


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(cut_at=st.integers(0, 10_000))
def test_any_truncation_of_graph_json_is_one_domain_error(pristine, tmp_path_factory, cut_at):
    ckpt = Path(shutil.copytree(pristine, tmp_path_factory.mktemp("cutjson") / "ckpt"))
    text = (ckpt / GRAPH_JSON).read_bytes()
    (ckpt / GRAPH_JSON).write_bytes(text[: min(cut_at, len(text.rstrip()) - 1)])  # a trailing newline is not damage
    with pytest.raises(OmniscsError) as info:
        load_graph(ckpt)
    assert len(str(info.value).splitlines()) == 1
