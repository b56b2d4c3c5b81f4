"""refit: the fit's own loop on an already fitted graph, with some rows of a node trainable and the rest fixed."""
import numpy as np
import pytest
import torch

from omniscs.nsg.graph import BACKGROUND, agent_key
from omniscs.nsg.observations import Observations
from omniscs.nsg.train import FitDiverged, fit_scene, refit
from omniscs.plan import make_plan
from omniscs.scene import load_scene
from tests.nsg_fixtures import tiny_fit_config, write_nsg_scene


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    scene = load_scene(write_nsg_scene(tmp_path_factory.mktemp("refit") / "in"))
    config = tiny_fit_config(20)
    plan = make_plan(scene, config=config.plan)
    return scene, plan, config, fit_scene(scene, config, plan, evaluate=False).graph


def _sampler(scene, plan, nan_rows: int = 0):
    obs = Observations(scene, plan.cameras)
    views = [(c, f) for f in plan.train_frames for c in plan.cameras]

    def sample(i, step):
        cam, f = views[i]
        target = obs.image(cam, f).clone()
        target[:nan_rows] = float("nan")  # unsupervised pixels
        return obs.view(cam, f), target, 1, None
    return len(views), sample


def test_only_the_trainable_rows_change_and_the_sky_and_exposure_are_held(fitted):
    import dataclasses

    scene, plan, config, graph = fitted
    n = len(graph.background)
    rows = torch.zeros(n, dtype=torch.bool)
    rows[: n // 3] = True
    frozen_agents = {agent_key(a.track_id): torch.zeros(len(a.gaussians), dtype=torch.bool) for a in graph.agents}
    cfg = dataclasses.replace(config, iterations=12)
    count, sample = _sampler(scene, plan, nan_rows=5)
    out, history = refit(graph, cfg, count, sample, {BACKGROUND: rows, **frozen_agents})
    before, after = graph.background, out.background
    # fixed rows are rendered first, unchanged; the trainable ones (no densification in 12 steps) follow
    assert torch.equal(after.means[: n - n // 3], before.means[~rows])
    assert not torch.equal(after.means[n - n // 3:], before.means[rows])
    assert torch.equal(out.sky.texture, graph.sky.texture)
    assert all(torch.equal(out.exposure[c], graph.exposure[c]) for c in graph.exposure)
    for a, b in zip(out.agents, graph.agents):
        assert torch.equal(a.gaussians.means, b.gaussians.means)
    assert history and all(np.isfinite(h["loss"]) for h in history)


def test_a_refit_that_blows_up_raises_and_returns_nothing(fitted):
    import dataclasses

    scene, plan, config, graph = fitted
    lr = dataclasses.replace(config.lr, sh_dc=1e4)  # colours run away: the loss explodes
    count, sample = _sampler(scene, plan)
    with pytest.raises(FitDiverged):
        refit(graph, dataclasses.replace(config, iterations=60, lr=lr, divergence_warmup=5), count, sample)
