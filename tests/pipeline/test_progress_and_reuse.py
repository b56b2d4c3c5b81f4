"""The one progress contract (a throttle in front of every sink) and the one reuse contract (stage key in
``stage.json``, written last)."""
import io
import json
import os
import re
import subprocess
import sys
from pathlib import Path

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


def test_throttle_passes_the_first_report_of_each_new_phase_of_a_stage():
    heard, clock = [], Clock()
    throttle = Throttled(lambda d, t, n: heard.append((d, t)), step_pct=10.0, min_interval_s=30.0, clock=clock)
    throttle(0, None, "started")
    for done in range(1, 21):  # replayed views
        throttle(done, 20)
    for done in range(1, 1001):  # then rendered variants: a new total, counted from the start again
        throttle(done, 1000)
    for done in range(1, 1001):  # then a second pass over as many steps: the count went back
        throttle(done, 1000)
    assert heard[:2] == [(0, None), (1, 20)] and (20, 20) in heard
    assert heard.count((1, 1000)) == 2 and heard.count((1000, 1000)) == 2
    assert len(heard) <= 2 + 11 + 2 * 11


def test_a_silent_stage_is_reminded_only_after_the_interval_with_its_latest_count():
    heard, clock = [], Clock()
    throttle = Throttled(lambda d, t, n: heard.append((d, t, n)), step_pct=10.0, min_interval_s=30.0, clock=clock)
    assert not throttle.remind("still running")  # nothing reported yet
    throttle(0, None, "started")
    clock.now = 29.0
    assert not throttle.remind("still running after 29 s")
    clock.now = 31.0
    assert throttle.remind("still running after 31 s")
    clock.now = 45.0
    assert not throttle.remind("still running after 45 s")  # the reminder counts as a line
    throttle(1, 2, "variant 1")  # a report after a reminder: a new phase (a total), heard at once
    clock.now = 50.0
    throttle(2, 200, "step 2")  # a new phase: heard
    clock.now = 60.0
    throttle(3, 200, "step 3")  # too little, too soon
    clock.now = 81.0
    assert throttle.remind("still running after 81 s")  # it moved: the interval rule passes its own report
    assert heard == [(0, None, "started"), (0, None, "still running after 31 s"), (1, 2, "variant 1"),
                     (2, 200, "step 2"), (3, 200, "step 3")]
    out = io.StringIO()
    LineProgress("s0 behavior", out)(0, None, "still running after 31 s")
    LineProgress("s0 behavior", out)(0, None)
    assert out.getvalue() == "s0 behavior: still running after 31 s\ns0 behavior: 0\n"


# ----------------------------------------------------------------------------- a run's feed (stages elsewhere -> CLI)
def test_a_feed_reader_returns_each_report_once_in_order_and_waits_for_a_line_being_written(tmp_path):
    from omniscs.progress import FeedReader, FeedReport, FeedWriter

    writer, reader = FeedWriter(tmp_path, "s0 fit"), FeedReader(tmp_path)
    writer(1, 10, "loss 0.5")
    writer(5, 10, "loss 0.2")
    assert [(r.label, r.done, r.total, r.note) for r in reader.read()] == [("s0 fit", 1, 10, "loss 0.5"),
                                                                            ("s0 fit", 5, 10, "loss 0.2")]
    assert reader.read() == []
    with open(writer.path, "a") as stream:  # a writer caught in the middle of a line
        stream.write('{"label": "s0 fit", "done": 7,')
    assert reader.read() == []
    with open(writer.path, "a") as stream:
        stream.write(' "total": 10, "note": "", "event": "progress", "at": 1.0}\n')
    assert reader.read() == [FeedReport("s0 fit", 7, 10, "", at=1.0)]
    later, sooner = FeedWriter(tmp_path, "s0 fit"), FeedWriter(tmp_path, "s0 behavior")
    later.write(FeedReport("s0 fit", 10, 10, "", at=3.0))
    sooner.write(FeedReport("s0 behavior", 0, None, "started", "start", at=4.0))
    assert [r.label for r in reader.read()] == ["s0 fit", "s0 behavior"]  # across files, in the order written


def test_a_stage_writes_no_feed_unless_a_command_watches_its_run(tmp_path):
    from omniscs.locks import clean_stale_temps
    from omniscs.progress import FEED_ROOT, FeedReader, no_progress, stage_feed, watched_run
    from omniscs.storage import temp_owner

    for run_id in ("r1", None):
        with stage_feed(tmp_path, run_id, "s0 fit") as progress:
            assert progress is no_progress
    assert not (tmp_path / FEED_ROOT).exists()
    with watched_run(tmp_path, "r1") as feed:
        assert temp_owner(feed) == os.getpid()  # a temporary of the watcher: clean_stale_temps removes it once it died
        assert clean_stale_temps(tmp_path) == []  # ... and not while it lives
        with stage_feed(tmp_path, "r2", "s0 fit") as progress:
            assert progress is no_progress  # another run is not watched
        with pytest.raises(RuntimeError), stage_feed(tmp_path, "r1", "s0 fit") as progress:
            progress(1, 4)
            raise RuntimeError("the stage failed")
        assert [(r.event, r.done) for r in FeedReader(feed).read()] == [("start", 0), ("progress", 1), ("end", 0)]
    assert not (tmp_path / FEED_ROOT).exists()


def test_a_stage_in_another_process_shows_as_throttled_lines_of_the_command_that_watches_its_run(tmp_path, capsys):
    from omniscs.cli.common import run_progress

    ROOT = Path(__file__).resolve().parents[2]
    stage = ("import sys; from omniscs.progress import stage_feed\n"
             "with stage_feed(sys.argv[1], 'r1', 'syn-a fit') as p:\n"
             "    for i in range(1, 3001): p(i, 3000, f'loss {1 / i:.4f}')\n")
    with run_progress(tmp_path, "r1"):
        proc = subprocess.run([sys.executable, "-c", stage, str(tmp_path)], cwd=ROOT, capture_output=True, text=True,
                              env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=120)
        assert proc.returncode == 0, proc.stderr
    started, *lines = capsys.readouterr().err.splitlines()
    assert started == "syn-a fit: started"
    pcts = [int(re.fullmatch(r"syn-a fit: \d+/3000 \((\d+)%\)  loss [\d.]+", line).group(1)) for line in lines]
    assert pcts[0] == 0 and pcts[-1] == 100 and lines[-1].startswith("syn-a fit: 3000/3000")
    assert 11 <= len(lines) <= 12 and all(b - a >= 10 for a, b in zip(pcts, pcts[1:-1]))  # every 10 %, no flood
    assert not (tmp_path / "progress").exists()


def test_plain_lines_of_a_command_keep_one_throttle_per_label(capsys):
    from omniscs.cli.common import Bars

    bars = Bars(None)
    assert bars.sink("s0 fit") is bars.sink("s0 fit")
    for done in range(1, 501):  # a caller that asks for its sink at every step (scs train-behavior does)
        bars.sink("s0 fit")(done, 500)
    lines = capsys.readouterr().err.splitlines()
    assert lines[0] == "s0 fit: 1/500 (0%)" and lines[-1] == "s0 fit: 500/500 (100%)" and len(lines) == 11
