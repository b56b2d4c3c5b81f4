"""What a UniAD export says about itself when its defaults would mislead: an empty val pickle, and motion anchors that
are straight lines rather than learnt from the data (short logs complete their futures at constant velocity)."""
import logging
import pickle

import numpy as np
import pytest

from omniscs.export import export_scenes
from omniscs.export.uniad import ANCHOR_FILE, UniADConfig, extended_futures, motion_anchors
from tests.conftest import write_tiny_scene


def _load(path):
    with open(path, "rb") as fh:
        return pickle.load(fh)


def test_an_export_without_val_scenes_warns_with_the_fix_and_with_them_does_not(tmp_path, caplog):
    store = write_tiny_scene(tmp_path / "tiny", n_frames=11, scene_id="tiny-val")
    with caplog.at_level(logging.WARNING, logger="omniscs.export.uniad"):
        out = export_scenes([store], "uniad", tmp_path / "data")
    said = [r.getMessage() for r in caplog.records if "val pickle is empty" in r.getMessage()]
    assert len(said) == 1 and "--val-scene" in said[0] and "tiny-val" in said[0]
    assert not _load(out / "infos" / "nuscenes_infos_temporal_val.pkl")["infos"]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="omniscs.export.uniad"):
        out = export_scenes([store], "uniad", tmp_path / "data2", val_scenes=["tiny-val"])
    assert not any("val pickle" in r.getMessage() for r in caplog.records)
    assert len(_load(out / "infos" / "nuscenes_infos_temporal_val.pkl")["infos"]) == 3


def test_partial_futures_are_continued_at_their_last_velocity():
    steps = 6
    future = np.stack([np.zeros(steps), 2.0 * np.arange(1, steps + 1)], 1)  # 2 m per step along +y
    known = np.array([[True] * 3 + [False] * 3, [True] + [False] * 5])
    out = extended_futures(np.stack([future * np.where(k[:, None], 1, 0) for k in known]), known, min_known=2)
    assert out.shape == (1, steps, 2) and np.allclose(out[0], future)  # the 1-step one is too short: left out
    assert extended_futures(np.zeros((0, steps, 2)), np.zeros((0, steps), bool), 2).shape == (0, steps, 2)


def _partial_infos(rng, n_agents: int, known_steps: int):
    """Cars whose futures are known for ``known_steps`` of 16 steps (a short log), straight at spread speeds."""
    speeds = rng.uniform(2, 12, n_agents)
    steps = np.arange(1, 17) * 0.5
    fut = np.stack([np.stack([rng.normal(0, 0.3) * steps, v * steps], 1) for v in speeds])
    mask = np.zeros_like(fut)
    mask[:, :known_steps] = 1.0
    return [{"gt_names": np.array(["car"] * n_agents), "gt_velocity": np.stack([np.zeros(n_agents), speeds], 1),
             "fut_traj": fut * mask, "fut_traj_valid_mask": mask}]


def test_short_logs_give_anchors_from_their_extended_futures_and_a_warning_for_empty_groups(caplog):
    infos = _partial_infos(np.random.default_rng(1), 30, known_steps=6)  # 3 s known of the anchors' 6 s
    with caplog.at_level(logging.WARNING, logger="omniscs.export.uniad"):
        anchors = motion_anchors(infos, UniADConfig())
    assert anchors["sample_counts"] == [0, 0, 0, 0] and anchors["extended_counts"] == [30, 0, 0, 0]
    assert anchors["fallback"] == [False, True, True, True]
    vehicle = anchors["anchors_all"][0]
    ends = np.sort(vehicle[:, -1, 1])
    assert vehicle.shape == (6, 12, 2) and ends[0] < 6 * 4 and ends[-1] > 6 * 9  # the speeds' spread, over 6 s
    said = [r.getMessage() for r in caplog.records if "motion anchors" in r.getMessage()]
    assert len(said) == 1 and "bike (0 complete, 0 extended)" in said[0] and "vehicle" not in said[0]


def test_an_export_of_a_short_log_warns_that_its_anchors_are_straight_lines(tmp_path, caplog):
    store = write_tiny_scene(tmp_path / "tiny", n_frames=11, scene_id="tiny-anchor")
    with caplog.at_level(logging.WARNING, logger="omniscs.export.uniad"):
        out = export_scenes([store], "uniad", tmp_path / "data", val_scenes=["tiny-anchor"])
    anchors = _load(out / "others" / ANCHOR_FILE)
    assert anchors["fallback"] == [True] * 4
    said = [r.getMessage() for r in caplog.records if "motion anchors" in r.getMessage()]
    assert len(said) == 1 and "straight lines" in said[0] and "61 frames at 10 Hz" in said[0]


@pytest.mark.parametrize("value", [0, -1, 1.5])
def test_a_bad_anchor_min_known_is_a_clear_error(value):
    from omniscs.errors import OmniscsError

    with pytest.raises(OmniscsError, match="anchor_min_known must be an integer >= 1"):
        UniADConfig(anchor_min_known=value)
