"""Quality gates: each variant's verdict with its reasons, the card's requested / produced / rejected counts and
its warnings, and the generator that tries further candidates until enough pass."""
from __future__ import annotations

import math

import pytest

from omniscs.annotate.dataset import card_warnings, gate_record, gate_summary, lidar_coverage
from omniscs.errors import OmniscsError
from omniscs.gates import GateConfig, Verdict, behaviour_verdict, edited_visible_frames, rendered_verdict
from omniscs.pipeline.request import SceneRequest


def test_a_behaviour_variant_without_contact_fails_and_says_how_close_it_came():
    v = behaviour_verdict({"success": False, "min_distance_m": 6.62, "plausible": True}, GateConfig())
    assert not v.passed and v.reasons == ("no collision within the horizon (closest approach 6.6 m between centres)",)


def test_an_unreachable_adversary_is_named_as_the_reason_with_the_horizon():
    spec = {"success": False, "min_distance_m": 43.0, "plausible": True, "reachable": False, "now_step": 9,
            "dt": 0.1, "timestamps_us": list(range(20))}
    (reason,) = behaviour_verdict(spec, GateConfig()).reasons
    assert reason == ("no collision within the horizon (closest approach 43.0 m between centres); no vehicle could "
                      "reach the ego's path within the 1.0 s horizon (a longer log gives a longer one)")


def test_a_near_miss_passes_only_when_the_request_allows_one():
    spec = {"success": False, "min_distance_m": 1.2, "plausible": True}
    assert not behaviour_verdict(spec, GateConfig()).passed
    assert behaviour_verdict(spec, GateConfig(near_miss_m=1.5)).passed
    farther = behaviour_verdict(dict(spec, min_distance_m=2.0), GateConfig(near_miss_m=1.5))
    assert not farther.passed and "near-miss (<= 1.5 m)" in farther.reasons[0]


def test_an_implausible_collision_fails_with_its_violations():
    v = behaviour_verdict({"success": True, "min_distance_m": 0.0, "plausible": False,
                           "violations": ["off_road", "accel"]}, GateConfig())
    assert v.reasons == ("implausible adversary (off_road, accel)",)
    assert behaviour_verdict({"success": True, "plausible": False}, GateConfig(require_plausible=False)).passed


def _ann(frame, track, pixels, fraction, camera="CAM_FRONT"):
    return {"frame_idx": frame, "track_id": track, "mask_pixels": pixels, "visible_fraction": fraction,
            "camera": camera}


def test_an_object_counts_as_visible_only_in_frames_with_enough_pixels_and_unoccluded_share():
    gates = GateConfig(min_mask_pixels=100, min_visible_fraction=0.25)
    rows = [_ann(0, 7, 500, 0.9), _ann(0, 7, 500, 0.9, "CAM_FRONT_LEFT"),  # one frame, two cameras: one frame
            _ann(1, 7, 99, 1.0), _ann(2, 7, 800, 0.2), _ann(3, 7, 100, 0.25), _ann(4, 8, 900, 1.0)]
    assert edited_visible_frames(rows, 7, gates) == 2


def test_a_hidden_appearance_object_fails_and_a_visible_one_passes():
    gates = GateConfig(min_visible_frames=3)
    hidden = rendered_verdict({"level": "appearance", "edited_visible_frames": 0, "fidelity_psnr": 25.0}, gates)
    assert not hidden.passed and "visible in 0 frame(s), fewer than 3" in hidden.reasons[0]
    assert rendered_verdict({"level": "appearance", "edited_visible_frames": 3, "fidelity_psnr": 25.0}, gates).passed


def test_fidelity_is_judged_exactly_where_a_reference_exists_and_by_the_proxies_elsewhere():
    gates = GateConfig(min_psnr_db=20.0, min_logged_psnr_db=16.0, max_feature_drift=0.1)
    assert "below 20 dB" in rendered_verdict({"level": "behaviour", "fidelity_psnr": 19.9}, gates).reasons[0]
    recorded = rendered_verdict({"level": "behaviour", "fidelity_psnr": None, "logged_psnr": 15.0,
                                 "feature_drift": 0.2}, gates)
    assert len(recorded.reasons) == 2
    assert rendered_verdict({"level": "behaviour", "fidelity_psnr": None, "logged_psnr": 17.0,
                             "feature_drift": 0.05}, gates).passed


def test_a_behaviour_variant_without_an_ego_solution_fails_unless_the_gate_is_off():
    assert not rendered_verdict({"level": "behaviour", "ego_solved": False}, GateConfig()).passed
    assert rendered_verdict({"level": "behaviour", "ego_solved": False}, GateConfig(require_ego_solution=False)).passed


def test_verdicts_combine_their_reasons():
    both = Verdict.of(["a"]) & Verdict.of(["b"])
    assert not both.passed and both.reasons == ("a", "b")
    assert (Verdict(True) & Verdict(True)).passed
    assert Verdict.from_dict(both.to_dict()) == both


@pytest.mark.parametrize("field, value", [("near_miss_m", -1.0), ("near_miss_m", math.inf),
                                          ("min_psnr_db", math.nan), ("min_visible_fraction", 1.5),
                                          ("min_visible_frames", -1)])
def test_a_bad_gate_is_one_clear_error(field, value):
    with pytest.raises(OmniscsError, match=field):
        GateConfig(**{field: value})


def test_the_request_carries_its_gates_and_refuses_non_finite_floors():
    gates = SceneRequest(near_miss_m=2.0, min_visible_frames=5, min_fidelity_psnr=18.0).gates()
    assert (gates.near_miss_m, gates.min_visible_frames, gates.min_psnr_db) == (2.0, 5, 18.0)
    with pytest.raises(OmniscsError, match="near_miss_m"):
        SceneRequest(near_miss_m=math.inf)
    with pytest.raises(OmniscsError, match="variant_budget"):
        SceneRequest(variant_budget=0)


def _rows(scene, variants, rejected=(), wanted=None):
    return {"variants": [dict(v, scene_id=scene) for v in variants], "rejected": list(rejected), "wanted": wanted,
            "spare": []}


def test_the_card_counts_requested_produced_and_rejected_per_level_and_warns_in_plain_words():
    a = gate_record(_rows("s1", [{"variant_id": "v00", "level": "behaviour",
                                  "gate": {"passed": False, "reasons": ["no collision within the horizon"]}},
                                 {"variant_id": "a000", "level": "appearance", "gate": {"passed": True, "reasons": []}}],
                          rejected=[{"variant_id": "v01", "level": "behaviour", "passed": False,
                                     "reasons": ["no collision within the horizon"]}],
                          wanted={"behaviour": 2, "appearance": 1}))
    gates = gate_summary([a], keep_failed=True)
    assert gates["requested"] == {"behaviour": 2, "appearance": 1, "designed": 0}
    assert gates["produced"] == {"behaviour": 0, "appearance": 1, "designed": 0}
    assert gates["rejected"] == {"behaviour": 2, "appearance": 0, "designed": 0} and gates["tried"]["behaviour"] == 2
    assert gates["failed_kept"] == 1  # only the rendered one can be in the dataset
    lidar = lidar_coverage([])
    warnings = card_warnings({"dropped_frames": 0}, gates, lidar)
    assert "0 of 2 requested behaviour variant(s) passed the quality gates (2 tried)" in warnings
    assert "0 of 2 behaviour variant(s) reached a collision" in warnings
    assert any(w.startswith("1 variant(s) in this dataset failed") for w in warnings)


def test_lidar_coverage_counts_boxes_within_range():
    def box(frame, track, n, d):
        return {"store_id": "s", "frame_idx": frame, "track_id": track, "num_lidar_points": n,
                "visible_pixels": 10, "distance_m": d}
    rows = [box(0, 1, 5, 10.0), box(0, 2, 0, 20.0), box(0, 3, 0, 80.0), box(1, 1, -1, 10.0)]  # -1: not measured
    c = lidar_coverage(rows)
    assert (c["boxes"], c["with_points"], c["boxes_within"], c["with_points_within"]) == (3, 1, 2, 1)
    assert c["share_within"] == 0.5
    warnings = card_warnings({"dropped_frames": 0}, gate_summary([], False), c)
    assert warnings == ["only 1 of 2 boxes within 50 m have LiDAR points; nuScenes' evaluation and UniAD's "
                        "valid_flag drop the others"]


def test_lidar_coverage_counts_only_the_boxes_an_annotator_labels():
    def box(frame, track, n, pixels):
        return {"store_id": "s", "frame_idx": frame, "track_id": track, "num_lidar_points": n,
                "visible_pixels": pixels, "distance_m": 10.0}
    rows = [box(0, 1, 0, 0), box(1, 1, 0, 30), box(2, 1, 0, 0), box(3, 1, 4, 0), box(4, 1, 0, 0),
            # track 1: seen at 1 (camera) and 3 (LiDAR): frames 1..3 labelled; track 2: never captured
            box(0, 2, 0, 0), box(1, 2, 0, 0)]
    c = lidar_coverage(rows)
    assert (c["boxes"], c["with_points"], c["unlabelled"]) == (3, 1, 4)
    assert (c["boxes_within"], c["with_points_within"]) == (3, 1)


def test_a_spare_appearance_candidate_that_would_uncover_an_unrepaired_object_is_not_rendered(monkeypatch):
    from omniscs.pipeline import annotate

    uncovers = {"a000": (7,), "a001": (), "a002": (9,), "a003": (7,)}
    monkeypatch.setattr(annotate, "variant_uncovers", lambda scene, v: uncovers[v["variant_id"]])
    variants = [{"variant_id": "v00", "kind": "cut_in"}] + [{"variant_id": k, "kind": "appearance"} for k in uncovers]
    kept = annotate.without_unrepaired_spares(None, variants, n_requested=2, repaired={7})
    # a000 is requested (repaired for); a002 would uncover 9, which no repair covers; a003's object 7 is repaired
    assert [v["variant_id"] for v in kept] == ["v00", "a000", "a001", "a003"]


def test_a_designed_variant_names_its_least_visible_edited_track_when_it_fails():
    gates = GateConfig(min_visible_frames=3)
    hidden = rendered_verdict({"level": "designed", "edited_visible_frames": 1, "least_visible_track": 7}, gates)
    assert not hidden.passed and hidden.reasons[0].startswith("edited track 7 is visible in 1 frame(s), fewer than 3")
    assert rendered_verdict({"level": "designed", "edited_visible_frames": 3, "least_visible_track": 7},
                            gates).passed


def test_a_designed_variant_shows_every_edited_track_it_keeps_and_picks_the_new_path_as_adversary():
    from omniscs.scs.appearance.variants import designed_variant

    spec = [{"op": "insert", "track_id": 9, "asset_id": "pm-0123456789ab", "category": "truck",
             "pose": [1.0, 2.0, 1.5, 0.0], "roll_deg": 180.0},
            {"op": "translate", "track_id": 3, "longitudinal": 1.0},
            {"op": "remove", "track_id": 4},
            {"op": "set_trajectory", "track_id": 5, "waypoints": [[0.0, 0.0, 0.7, 0.0], None]}]
    v = designed_variant("scene-a", spec, pool=None)
    assert (v["variant_id"], v["kind"], v["adversary"], v["tracks"]) == ("d000", "designed", 5, [9, 3, 5])
    assert (v["object_id"], v["category"]) == ("pm-0123456789ab", "truck")
    assert designed_variant("scene-a", spec[1:3])["adversary"] == 3  # no new path, no object: the first edited
    with pytest.raises(OmniscsError, match="at least one edit"):
        designed_variant("scene-a", [])


def test_a_request_with_edits_alone_makes_a_dataset_and_without_them_is_refused():
    from omniscs.pipeline.request import RunRequest

    edits = [{"op": "translate", "track_id": 1, "longitudinal": 1.0}]
    assert RunRequest(sources=["syn:straight:0"], fit_preset="fast", annotate=True, edits=edits).annotate
    with pytest.raises(OmniscsError, match="or edits"):
        RunRequest.parse(dict(sources=["syn:straight:0"], fit_preset="fast", annotate=True))
