"""The traffic model: feasible decoding for any latent, finite outputs at the extremes, learning, checkpoints."""
import json

import pytest
import torch

from omniscs.errors import OmniscsError
from omniscs.pipeline.procedural import traffic_from_world
from omniscs.scs.behavior.checkpoint import DEFAULT_CHECKPOINT, load_traffic_model, save_checkpoint, training_record
from omniscs.scs.behavior.features import build_sample, collate
from omniscs.scs.behavior.kinematics import yaw_rate_bound
from omniscs.scs.behavior.model import ModelConfig, TrafficModel
from tests.behavior_fixtures import straight_world


@pytest.fixture(scope="module")
def batch():
    world = straight_world([{"x": 20.0, "y": 3.3, "speed": 9.0}, {"x": 60.0, "y": 6.6, "yaw": 3.1416, "speed": 7.0},
                            {"x": 35.0, "y": 12.5, "speed": 0.0}, {"x": 5_000.0, "y": 3.3, "speed": 9.0}])
    return collate([build_sample(traffic_from_world(world), 9, 10, 30)])


@pytest.mark.parametrize("scale", [0.0, 1.0, 100.0])
def test_decoded_trajectories_are_kinematically_feasible_for_any_latent(batch, scale):
    torch.manual_seed(0)
    model = TrafficModel(ModelConfig())
    with torch.no_grad():
        context, edges, mask = model.encode_past(batch)
        z = torch.randn(1, batch.node_mask.shape[1], model.config.latent) * scale
        dec = model.decode(context, z, batch, edges, mask)
    limits = model.config.limits
    v, w = dec.states[..., 3], dec.states[..., 4]
    assert torch.isfinite(dec.states).all()
    assert (v >= 0).all() and (v <= limits.max_speed).all()
    assert (w.abs() <= yaw_rate_bound(v, limits) + 1e-5).all()
    assert (dec.longitudinal_accel.abs() <= limits.max_decel + 1e-3).all()
    # the parked car (node 3) moves sideways only as far as rolling on the steering lock allows: |dy| <= k s² / 2
    assert batch.state0[0, 3, 3] == 0
    xy = torch.cat([batch.state0[0, 3, None, :2], dec.states[0, 3, :, :2]])
    travelled = torch.cumsum((xy[1:] - xy[:-1]).norm(dim=-1), 0)
    sideways = (dec.states[0, 3, :, 1] - batch.state0[0, 3, 1]).abs()
    assert (sideways <= 0.5 * limits.max_curvature * travelled ** 2 + 1e-3).all()


def test_a_scene_with_only_the_ego_gives_finite_losses():
    b = collate([build_sample(traffic_from_world(straight_world([])), 9, 10, 30)])
    torch.manual_seed(0)
    out = TrafficModel().losses(b, kl_weight=0.1, free_nats_per_dim=0.1)
    assert all(torch.isfinite(v) for v in out.values())


def test_training_steps_fit_a_small_batch(batch):
    torch.manual_seed(0)
    model = TrafficModel()
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    first = None
    for _ in range(40):
        out = model.losses(batch, kl_weight=0.01)
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
        first = first if first is not None else float(out["recon"].detach())
    assert float(out["recon"].detach()) < 0.5 * first


def test_checkpoints_round_trip_exactly(batch, tmp_path):
    torch.manual_seed(1)
    model = TrafficModel().eval()
    save_checkpoint(model, tmp_path / "ckpt", {"seed": 1, "command": "test"})
    loaded = load_traffic_model(tmp_path / "ckpt")
    with torch.no_grad():
        a = model.encode_past(batch)[0]
        b = loaded.encode_past(batch)[0]
    assert torch.equal(a, b) and training_record(tmp_path / "ckpt")["seed"] == 1


def test_a_missing_checkpoint_says_how_to_make_one(tmp_path):
    with pytest.raises(OmniscsError, match="train-behavior"):
        load_traffic_model(tmp_path / "nothing")


def test_the_shipped_checkpoint_records_how_it_was_made_and_beats_constant_velocity():
    record = json.loads((DEFAULT_CHECKPOINT / "training.json").read_text())
    assert record["seed"] == 0 and "omniscs scs train-behavior" in record["command"]
    assert (DEFAULT_CHECKPOINT / "model.safetensors").stat().st_size < 4_000_000
    moving = record["heldout_metrics"]["moving"]
    assert moving["agents"] > 100
    assert moving["posterior"]["ade"] < moving["constant_velocity"]["ade"]
    manoeuvres = record["heldout_manoeuvre_metrics"]["moving"]
    assert manoeuvres["posterior"]["ade"] < manoeuvres["prior_mean"]["ade"], "the latent carries the manoeuvre"
