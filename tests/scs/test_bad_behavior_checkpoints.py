"""Damaged traffic-model checkpoints: a truncated or garbled weights file, a config that is a list, mistyped, huge or
from another architecture, missing files, a folder that is not a checkpoint: each is one OmniscsError line, and
nothing is written while refusing it. Cases are damaged copies of the shipped 1 MB checkpoint."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from omniscs.errors import OmniscsError
from omniscs.scs.behavior.checkpoint import (DEFAULT_CHECKPOINT, MODEL_CONFIG, TRAINING, WEIGHTS, checkpoint_hash,
                                             load_traffic_model, training_record)
from tests.damage import cut, files_under, write


def config_change(change):
    def damage(ckpt: Path):
        cfg = json.loads((ckpt / MODEL_CONFIG).read_text())
        change(cfg)
        (ckpt / MODEL_CONFIG).write_text(json.dumps(cfg))
    return damage


def flip(name: str, where: float):
    def damage(ckpt: Path):
        data = bytearray((ckpt / name).read_bytes())
        data[int(len(data) * where)] ^= 0xFF
        (ckpt / name).write_bytes(bytes(data))
    return damage


CASES = {
    # the model config
    "config a list": (write(MODEL_CONFIG, b"[64, 32]"), r"model_config.json must be a JSON object of model settings; "
                                                        r"got a list"),
    "config a number": (write(MODEL_CONFIG, b"64"), r"model_config.json must be a JSON object .* got a int"),
    "config not JSON": (write(MODEL_CONFIG, b"{hidden: 64}"), r"model_config.json is not valid JSON"),
    "config cut in half": (cut(MODEL_CONFIG), r"model_config.json is not valid JSON"),
    "config binary": (write(MODEL_CONFIG, b"\xff\xfe\xfd"), r"model_config.json is not UTF-8 text \(byte 0 is 0xff\)"),
    "config missing": (lambda ckpt: (ckpt / MODEL_CONFIG).unlink(), r"no behaviour-model checkpoint in .* "
                                                                    r"\(model.safetensors and model_config.json"),
    "unknown config field": (config_change(lambda c: c.update(heads=8)), r"model_config.json: unknown field\(s\) "
                                                                         r"\['heads'\]"),
    "hidden a string": (config_change(lambda c: c.update(hidden="64")), r"field hidden must be an integer from 1 to "
                                                                        r"4096; got '64'"),
    "hidden a bool": (config_change(lambda c: c.update(hidden=True)), r"field hidden must be an integer .* got True"),
    "hidden huge": (config_change(lambda c: c.update(hidden=10**9)), r"field hidden must be an integer from 1 to 4096"),
    "latent zero": (config_change(lambda c: c.update(latent=0)), r"field latent must be an integer from 1"),
    "future steps negative": (config_change(lambda c: c.update(future_steps=-3)), r"field future_steps must be"),
    "dt NaN": (lambda ckpt: (ckpt / MODEL_CONFIG).write_text((ckpt / MODEL_CONFIG).read_text().replace(
        '"dt": 0.1', '"dt": NaN')), r"field dt must be a finite number; got nan"),
    "dt negative": (config_change(lambda c: c.update(dt=-0.1)), r"field dt must be a positive number"),
    "edge radius a list": (config_change(lambda c: c.update(edge_radius_m=[60])), r"field edge_radius_m must be a "
                                                                                 r"finite number"),
    "crop a list": (config_change(lambda c: c.update(crop=[1, 2])), r"field crop must be an object of finite numbers"),
    "crop unknown field": (config_change(lambda c: c["crop"].update(zoom=2)), r"field crop must be an object"),
    "crop of a billion cells": (config_change(lambda c: c["crop"].update(resolution_m=1e-7)),
                                r"field crop must be a patch of 1 to 4096 cells"),
    "limits with a string": (config_change(lambda c: c["limits"].update(max_speed="fast")),
                             r"field limits must be an object of finite numbers"),
    "another architecture": (config_change(lambda c: c.update(hidden=32)), r"is unreadable or does not match this "
                                                                          r"code .*; retrain it"),
    "config of fewer rounds": (config_change(lambda c: c.update(graph_rounds=1)), r"does not match this code"),
    # the weights
    "weights cut in half": (cut(WEIGHTS), r"model.safetensors is not a readable safetensors file"),
    "weights cut to 3 bytes": (cut(WEIGHTS, 3e-6), r"model.safetensors is not a readable safetensors file"),
    "weights empty": (write(WEIGHTS, b""), r"model.safetensors is not a readable safetensors file"),
    "weights garbage": (write(WEIGHTS, b"\x08\x00\x00\x00\x00\x00\x00\x00not json"), r"model.safetensors is not a "
                                                                                   r"readable safetensors file"),
    "weights header damaged": (flip(WEIGHTS, 0.00002), r"model.safetensors is not a readable safetensors file"),
    "weights of a torch pickle": (write(WEIGHTS, b"PK\x03\x04" + b"\x00" * 64), r"not a readable safetensors"),
    "weights missing": (lambda ckpt: (ckpt / WEIGHTS).unlink(), r"no behaviour-model checkpoint in"),
    "weights a folder": (lambda ckpt: ((ckpt / WEIGHTS).unlink(), (ckpt / WEIGHTS).mkdir()),
                         r"no behaviour-model checkpoint in"),
    "not a checkpoint folder": (lambda ckpt: [p.unlink() for p in ckpt.iterdir()],
                                r"no behaviour-model checkpoint in .*; train one with"),
}


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> Path:
    return Path(shutil.copytree(DEFAULT_CHECKPOINT, tmp_path_factory.mktemp("behavior") / "ckpt"))


@pytest.mark.parametrize("case", list(CASES))
def test_a_damaged_behavior_checkpoint_is_one_domain_error_line(case, pristine, tmp_path):
    ckpt = Path(shutil.copytree(pristine, tmp_path / "ckpt"))
    damage, message = CASES[case]
    damage(ckpt)
    before = files_under(tmp_path)
    with pytest.raises(OmniscsError, match=message) as info:
        load_traffic_model(ckpt)
    assert len(str(info.value).splitlines()) == 1
    assert files_under(tmp_path) == before


SIDE_CASES = {
    "training record not JSON": (cut(TRAINING), training_record, r"training.json is not valid JSON"),
    "training record a list": (write(TRAINING, b"[]"), training_record, r"training.json must be a JSON object"),
    "hash of a missing folder": (lambda ckpt: shutil.rmtree(ckpt), checkpoint_hash,
                                 r"cannot read .*model.safetensors .*pass a behaviour-model checkpoint folder"),
    "a file, not a folder": (lambda ckpt: shutil.rmtree(ckpt) or ckpt.write_text("x"), load_traffic_model,
                             r"no behaviour-model checkpoint in"),
}


@pytest.mark.parametrize("case", list(SIDE_CASES))
def test_side_files_of_a_checkpoint_are_refused_in_one_line(case, pristine, tmp_path):
    ckpt = Path(shutil.copytree(pristine, tmp_path / "ckpt"))
    damage, read, message = SIDE_CASES[case]
    damage(ckpt)
    before = files_under(tmp_path)
    with pytest.raises(OmniscsError, match=message) as info:
        read(ckpt)
    assert len(str(info.value).splitlines()) == 1
    assert files_under(tmp_path) == before


def test_the_pristine_copy_loads(pristine):
    model = load_traffic_model(pristine)
    assert not model.training and checkpoint_hash(pristine) == checkpoint_hash(None)
    assert training_record(pristine) == training_record(None)


@pytest.fixture(scope="module")
def weight_bytes(pristine) -> bytes:
    return (pristine / WEIGHTS).read_bytes()


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(fraction=st.floats(0.0, 0.999))
def test_any_truncation_of_the_weights_is_one_domain_error(pristine, weight_bytes, tmp_path_factory, fraction):
    """Property: the weights file cut anywhere is refused with one OmniscsError line, never another exception."""
    ckpt = Path(shutil.copytree(pristine, tmp_path_factory.mktemp("cut") / "ckpt"))
    (ckpt / WEIGHTS).write_bytes(weight_bytes[: int(len(weight_bytes) * fraction)])
    with pytest.raises(OmniscsError) as info:
        load_traffic_model(ckpt)
    assert len(str(info.value).splitlines()) == 1
