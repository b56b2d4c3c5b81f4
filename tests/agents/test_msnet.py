"""MSNet: the batch-hard triplet loss in its intended form (hardest positive pulled, hardest negative pushed), a
network that gives unit vectors, and training that lowers the loss."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from omniscs.agents.degradation import Degradation
from omniscs.agents.msnet import MSNet, MSNetEmbedder, MSNetTrainConfig, batch_hard_triplet, train_msnet
from omniscs.errors import ValidationError


def test_batch_hard_triplet_takes_the_farthest_positive_and_the_nearest_negative():
    emb = torch.tensor([[0.0, 0.0], [1.0, 0.0], [3.0, 0.0], [1.5, 0.0]])
    labels = torch.tensor([0, 0, 0, 1])
    # anchor 0: hardest positive 3.0 (point 2), nearest negative 1.5 -> 0.5 + 3.0 - 1.5 = 2.0
    # anchor 1: positives 1.0 and 2.0 -> 2.0, negative 0.5 -> 0.5 + 2.0 - 0.5 = 2.0
    # anchor 2: positives 3.0 and 2.0 -> 3.0, negative 1.5 -> 2.0; anchor 3 has no positive: left out
    assert float(batch_hard_triplet(emb, labels, 0.5)) == pytest.approx(2.0)
    apart = torch.tensor([[0.0, 0.0], [0.1, 0.0], [5.0, 0.0], [5.1, 0.0]])
    assert float(batch_hard_triplet(apart, torch.tensor([0, 0, 1, 1]), 0.5)) == 0.0
    assert float(batch_hard_triplet(apart, torch.tensor([0, 0, 0, 0]), 0.5)) == 0.0  # no negatives: nothing to learn


def _crops(n_models=4, views=6, seed=0):
    rng = np.random.default_rng(seed)
    crops, labels = [], []
    for m in range(n_models):
        base = rng.integers(0, 256, 3)
        for _ in range(views):
            img = np.tile(base, (64, 64, 1)).astype(np.uint8)
            y, x = rng.integers(0, 40, 2)
            img[y:y + 24, x:x + 24] = 255 - base  # the model's pattern, somewhere
            crops.append(img)
            labels.append(m)
    return np.stack(crops), np.array(labels)


@pytest.mark.slow
def test_the_network_gives_unit_vectors_and_training_lowers_the_loss():
    crops, labels = _crops()
    net = MSNet()
    with torch.no_grad():
        out = net(torch.rand(3, 3, 64, 64))
    assert out.shape == (3, 128) and torch.allclose(out.norm(dim=1), torch.ones(3), atol=1e-5)
    trained, record = train_msnet(crops, labels, [Degradation(), Degradation(downsample=2, occlusion=0.2)],
                                  MSNetTrainConfig(steps=40, models_per_batch=4, views_per_model=4))
    assert record["loss_last"] < record["loss_first"]
    e = MSNetEmbedder(trained).embed(crops)
    assert e.shape == (len(crops), 128) and np.allclose(np.linalg.norm(e, axis=1), 1.0, atol=1e-5)
    with pytest.raises(ValidationError, match="at least two models"):
        train_msnet(crops[:6], labels[:6], [Degradation()], MSNetTrainConfig(steps=1))


def test_the_shipped_weights_load_and_say_how_they_were_made(tmp_path):
    import json

    from omniscs.agents.msnet import SHIPPED, load_msnet, shipped_embedder

    info = json.loads((SHIPPED / "training.json").read_text())
    assert info["command"] == "omniscs bench agents --train-msnet" and info["config"]["seed"] == 0
    assert info["data"]["worlds"] and info["n_assets"] > 100 and info["loss_last"] < info["loss_first"]
    embedder = shipped_embedder()
    crops = np.random.default_rng(0).integers(0, 255, (5, 64, 64, 3), dtype=np.uint8)
    emb = embedder.embed(crops)
    assert emb.shape == (5, 128) and np.allclose(np.linalg.norm(emb, axis=1), 1.0, atol=1e-5)
    assert embedder.cache_key.startswith("msnet-")
    with pytest.raises(ValidationError, match="no MSNet weights"):
        load_msnet(tmp_path)
