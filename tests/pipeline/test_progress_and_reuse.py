"""The one progress contract (a throttle in front of every sink) and the one reuse contract (stage key in
``stage.json``, written last)."""
import io
import json

import pytest

from omniscs.pipeline.reuse import STAGE_MANIFEST, StageKey, mark_done, produce, reusable
from omniscs.progress import LineProgress, Throttled, percent


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_throttle_passes_the_first_and_last_report_and_every_step_of_five_percent():
    heard, clock = [], Clock()
    throttle = Throttled(lambda d, t, n: heard.append(d), step_pct=5.0, min_interval_s=10.0, clock=clock)
    for done in range(1, 1001):
        throttle(done, 1000)
    assert heard[0] == 1 and heard[-1] == 1000
    assert 19 <= len(heard) <= 22  # about one report per 5 %, never one per step
    assert all(b - a >= 50 for a, b in zip(heard, heard[1:-1]))


def test_throttle_reports_slow_unknown_totals_by_time_and_never_repeats_an_unchanged_count():
    heard, clock = [], Clock()
    throttle = Throttled(lambda d, t, n: heard.append((d, n)), min_interval_s=10.0, clock=clock)
    throttle(1, None, "a")
    clock.now = 5.0
    throttle(2, None, "b")  # too soon
    clock.now = 11.0
    throttle(3, None, "c")
    clock.now = 30.0
    throttle(3, None, "c")  # no movement
    assert heard == [(1, "a"), (3, "c")]


def test_plain_lines_say_what_how_far_and_the_note():
    out = io.StringIO()
    LineProgress("fit s0", out)(3, 12, "loss 0.1")
    LineProgress("scan", out)(7)
    assert out.getvalue() == "fit s0: 3/12 (25%)  loss 0.1\nscan: 7\n"
    assert percent(5, 0) == 0.0 and percent(20, 10) == 100.0 and percent(-1, 10) == 0.0


def test_a_stage_key_changes_with_inputs_config_version_and_stage_but_not_between_calls():
    key = StageKey.of("fit", 1, {"scene": "abc"}, {"iterations": 10})
    assert key == StageKey.of("fit", 1, {"scene": "abc"}, {"iterations": 10})
    others = [StageKey.of("fit", 1, {"scene": "abd"}, {"iterations": 10}),
              StageKey.of("fit", 1, {"scene": "abc"}, {"iterations": 11}),
              StageKey.of("fit", 2, {"scene": "abc"}, {"iterations": 10}),
              StageKey.of("plan", 1, {"scene": "abc"}, {"iterations": 10})]
    assert len({key.digest, *(k.digest for k in others)}) == 5 and len(key.short) == 12


def test_a_produced_folder_is_reused_only_under_its_own_key(tmp_path):
    key = StageKey.of("preview", 1, "scene", {})
    out = tmp_path / "previews" / "s"
    manifest = produce(out, key, lambda tmp: ((tmp / "a.txt").write_text("x"), {"a": "a.txt"})[1])
    assert manifest["outputs"] == {"a": "a.txt"} and (out / "a.txt").read_text() == "x"
    assert reusable(out, key)["key"] == key.digest
    assert reusable(out, StageKey.of("preview", 1, "other scene", {})) is None
    assert reusable(out, StageKey.of("preview", 2, "scene", {})) is None


def test_a_failed_stage_leaves_nothing_and_a_damaged_manifest_is_not_reused(tmp_path):
    key = StageKey.of("behavior", 1, "scene", {})
    out = tmp_path / "v"

    def fail(tmp):
        (tmp / "half.json").write_text("{")
        raise RuntimeError("interrupted")

    with pytest.raises(RuntimeError):
        produce(out, key, fail)
    assert not out.exists() and not list(tmp_path.iterdir())
    out.mkdir()
    (out / STAGE_MANIFEST).write_text("{not json")
    assert reusable(out, key) is None
    mark_done(out, key, {}, 1.0)
    assert json.loads((out / STAGE_MANIFEST).read_text())["stage"] == "behavior" and reusable(out, key)
