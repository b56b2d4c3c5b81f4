"""Edit specs: every malformed edit (the JSON ``--edit`` takes, dicts, edit objects) is one OmniscsError line that
names the edit and field; good edits still parse, and their values come out normalised."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from omniscs.edits import (MAX_TRACK_ID, Insert, Remove, Rotate, SetTrajectory, Translate, edit_from_dict, edit_to_dict,
                           parse_edits)
from omniscs.errors import OmniscsError

INSERT = {"op": "insert", "track_id": 50, "asset_id": "sedan-0001", "category": "car", "pose": [1.0, 2.0, 0.8, 0.0]}

#: id -> (what parse_edits is given, a regex the one-line message must match)
CASES = {
    # not an edit at all
    "a bare number": ("5", r"edits must be one edit object .* got 5"),
    "a JSON string": ('"remove"', r"edits must be one edit object .* got 'remove'"),
    "JSON null": ("null", r"edits must be one edit object .* got None"),
    "not JSON": ("[{op: remove}]", r"edit list is not valid JSON"),
    "truncated JSON": ('[{"op": "remove", "track_id": 1', r"edit list is not valid JSON"),
    "not UTF-8": (b"\xff\xfe[", r"edit list is not UTF-8"),
    "a list holding a number": ("[5]", r"edit 0: an edit must be a JSON object with an 'op' field"),
    "a list holding a list": ('[[{"op": "remove", "track_id": 1}]]', r"edit 0: an edit must be a JSON object"),
    "no op": ('{"track_id": 1}', r"edit 0: an edit must be a JSON object with an 'op' field"),
    # op and fields
    "unknown op": ('{"op": "fly", "track_id": 1}', r"edit 0: unknown edit op 'fly'; use one of"),
    "op of the wrong type": ('{"op": 3, "track_id": 1}', r"unknown edit op 3"),
    "unknown field": ('{"op": "remove", "track_id": 1, "dx": 3}', r"edit 0 \(remove\): unknown field\(s\) \['dx'\]"),
    "misspelt field": ('{"op": "translate", "track_id": 1, "laterl": 2}', r"unknown field\(s\) \['laterl'\]"),
    "missing track id": ('{"op": "remove"}', r"edit 0 \(remove\): missing field\(s\) \['track_id'\]"),
    "missing asset id": ('{"op": "replace_model", "track_id": 1}', r"missing field\(s\) \['asset_id'\]"),
    "missing waypoints": ('{"op": "set_trajectory", "track_id": 1}', r"missing field\(s\) \['waypoints'\]"),
    "second edit is bad": ('[{"op": "remove", "track_id": 1}, {"op": "remove", "track_id": "2"}]',
                           r"edit 1 \(remove\): field track_id must be an integer"),
    # track ids
    "track id true": ('{"op": "remove", "track_id": true}', r"field track_id must be an integer .* got True"),
    "track id false": ('{"op": "remove", "track_id": false}', r"field track_id must be an integer .* got False"),
    "track id string": ('{"op": "remove", "track_id": "1"}', r"field track_id must be an integer .* got '1'"),
    "track id float": ('{"op": "remove", "track_id": 1.0}', r"field track_id must be an integer .* got 1.0"),
    "track id negative": ('{"op": "remove", "track_id": -1}', r"field track_id must be an integer from 0 .* got -1"),
    "track id huge": (json.dumps({"op": "remove", "track_id": 2**70}), r"field track_id must be an integer from 0 to"),
    "track id null": ('{"op": "remove", "track_id": null}', r"field track_id must be an integer .* got None"),
    # amounts
    "string amount": ('{"op": "translate", "track_id": 1, "dx": "3"}', r"unknown field\(s\) \['dx'\]"),
    "string lateral": ('{"op": "translate", "track_id": 1, "lateral": "3"}',
                       r"field lateral must be a finite number of metres .* got '3'"),
    "bool amount": ('{"op": "translate", "track_id": 1, "lateral": true}', r"field lateral must be a finite number"),
    # JSON's non-numbers and overflowing or hostile numbers are refused by the reader, before any field check
    "NaN amount": ('{"op": "translate", "track_id": 1, "longitudinal": NaN}', r"the edit list holds NaN, which is not"),
    "Infinity amount": ('{"op": "rotate", "track_id": 1, "yaw_deg": Infinity}', r"the edit list holds Infinity, "),
    "-Infinity amount": ('{"op": "translate", "track_id": 1, "vertical": -Infinity}', r"the edit list holds -Infinity"),
    "overflowing amount": ('{"op": "translate", "track_id": 1, "vertical": 1e400}', r"holds a number too large"),
    "deeply nested": ("[" * 100_000, r"the edit list is nested more than 256 deep"),
    "a 5000-digit track id": ('{"op": "remove", "track_id": ' + "7" * 5000 + "}", r"holds an integer of 5000 digits"),
    "huge shift": ('{"op": "translate", "track_id": 1, "lateral": 1e9}', r"from -1000 to 1000; got 1000000000.0"),
    "huge angle": ('{"op": "rotate", "track_id": 1, "roll_deg": 7200}', r"field roll_deg must be .* degrees from -360"),
    "null amount": ('{"op": "rotate", "track_id": 1, "pitch_deg": null}', r"field pitch_deg must be a finite number"),
    "list amount": ('{"op": "rotate", "track_id": 1, "yaw_deg": [90]}', r"field yaw_deg must be a finite number"),
    # names
    "asset id a number": ('{"op": "replace_model", "track_id": 1, "asset_id": 7}', r"field asset_id must be a non-empty"),
    "asset id empty": ('{"op": "replace_model", "track_id": 1, "asset_id": ""}', r"field asset_id must be a non-empty"),
    "unknown category": (json.dumps({**INSERT, "category": "spaceship"}), r"unknown category 'spaceship'"),
    # poses, waypoints, sizes
    "insert without pose": (json.dumps({k: v for k, v in INSERT.items() if k != "pose"}),
                            r"an insert needs exactly one of 'pose'"),
    "insert with pose and waypoints": (json.dumps({**INSERT, "waypoints": [[0, 0, 0, 0]]}),
                                       r"an insert needs exactly one of 'pose'"),
    "pose of 3 numbers": (json.dumps({**INSERT, "pose": [1, 2, 3]}), r"field pose must be 4 numbers"),
    "pose with a string": (json.dumps({**INSERT, "pose": [1, 2, "3", 0]}), r"field pose must be 4 numbers"),
    "pose with NaN": ('{"op": "insert", "track_id": 5, "asset_id": "a", "category": "car", "pose": [0, NaN, 0, 0]}',
                      r"the edit list holds NaN"),
    "pose 10,000 km away": (json.dumps({**INSERT, "pose": [1e7, 0, 0, 0]}), r"field pose must be finite, with \|x\|"),
    "pose a dict": (json.dumps({**INSERT, "pose": {"x": 1}}), r"field pose must be 4 numbers"),
    "size negative": (json.dumps({**INSERT, "size": [4.5, -1.9, 1.6]}), r"field size must be 3 numbers .* above 0"),
    "size of 2": (json.dumps({**INSERT, "size": [4.5, 1.9]}), r"field size must be 3 numbers"),
    "size huge": (json.dumps({**INSERT, "size": [4.5, 1.9, 1e6]}), r"field size must be 3 numbers .* at most 100 m"),
    "waypoints not a list": ('{"op": "set_trajectory", "track_id": 1, "waypoints": 3}',
                             r"field waypoints must be a list of 1 to"),
    "waypoints empty": ('{"op": "set_trajectory", "track_id": 1, "waypoints": []}', r"field waypoints must be a list"),
    "waypoint of 3": ('{"op": "set_trajectory", "track_id": 1, "waypoints": [[0, 0, 0, 0], [1, 2, 3]]}',
                      r"waypoint 1 must be 4 numbers"),
    "waypoint with Infinity": ('{"op": "set_trajectory", "track_id": 1, "waypoints": [[0, 0, 0, Infinity]]}',
                               r"the edit list holds Infinity"),
    "waypoint of 1e400": ('{"op": "set_trajectory", "track_id": 1, "waypoints": [[0, 0, 0, 1e400]]}',
                          r"the edit list holds a number too large for a float \(1e400\)"),
    "waypoint of NaN (an object)": ([SetTrajectory(1, ((0.0, 0.0, 0.0, float("nan")),))], r"waypoint 0 must be finite"),
    "waypoint a string": ('{"op": "set_trajectory", "track_id": 1, "waypoints": ["0 0 0 0"]}',
                          r"waypoint 0 must be 4 numbers"),
    # edit objects are checked as JSON is
    "object with a bool track id": ([Remove(True)], r"field track_id must be an integer .* got True"),
    "object with a NaN amount": ([Translate(1, longitudinal=float("nan"))], r"field longitudinal .* got nan"),
    "object with a string amount": ([Rotate(1, yaw_deg="90")], r"field yaw_deg must be a finite number .* got '90'"),
    "object with a huge track id": ([Remove(MAX_TRACK_ID + 1)], r"field track_id must be an integer from 0"),
    "object with a short waypoint": ([SetTrajectory(1, ((0.0, 0.0, 0.0),))], r"waypoint 0 must be 4 numbers"),
    "a set of edits": ({1, 2}, r"edits must be one edit object"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_bad_edit_is_one_line_naming_the_edit_and_field(case, tmp_path):
    given_value, message = CASES[case]
    before = sorted(tmp_path.rglob("*"))
    with pytest.raises(OmniscsError, match=message) as info:
        parse_edits(given_value)
    assert len(str(info.value).splitlines()) == 1
    assert sorted(tmp_path.rglob("*")) == before


def test_the_cli_edit_option_refuses_a_number_in_one_line(tmp_path):
    from omniscs.cli.common import read_edits

    with pytest.raises(OmniscsError, match="edits must be one edit object") as info:
        read_edits("5")
    assert len(str(info.value).splitlines()) == 1
    spec = tmp_path / "edits.json"
    spec.write_text('{"op": "remove", "track_id": true}')
    with pytest.raises(OmniscsError, match="track_id must be an integer"):
        read_edits(f"@{spec}")


def test_good_edits_parse_and_come_out_normalised():
    edits = parse_edits(json.dumps([
        {"op": "translate", "track_id": 1, "lateral": 3},
        {"op": "rotate", "track_id": 1, "yaw_deg": 270},
        {"op": "remove", "track_id": 0},
        {"op": "replace_model", "track_id": 2, "asset_id": "nsg:1"},
        {"op": "set_trajectory", "track_id": 2, "waypoints": [[20, 3.3, 0.8, 0.1], None]},
        {**INSERT, "size": [4, 2, 1.5], "roll_deg": 180},
    ]))
    assert [e.op for e in edits] == ["translate", "rotate", "remove", "replace_model", "set_trajectory", "insert"]
    assert edits[0] == Translate(1, lateral=3.0) and isinstance(edits[0].lateral, float)
    assert edits[4].waypoints == ((20.0, 3.3, 0.8, 0.1), None)
    assert edits[5] == Insert(50, "sedan-0001", "car", pose=(1.0, 2.0, 0.8, 0.0), size=(4.0, 2.0, 1.5), roll_deg=180.0)
    assert parse_edits([edit_to_dict(e) for e in edits]) == edits  # a round trip through JSON form
    assert parse_edits([Remove(np.int64(3))]) == [Remove(3)]  # numpy ints are ints
    assert parse_edits("[]") == [] and parse_edits({"op": "remove", "track_id": 4}) == [Remove(4)]


@settings(max_examples=150, deadline=None)
@given(st.dictionaries(st.sampled_from(["op", "track_id", "lateral", "yaw_deg", "asset_id", "pose", "waypoints",
                                        "size", "category", "extra"]),
                       st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=5),
                                 st.lists(st.floats(), max_size=5), st.sampled_from(["remove", "translate", "insert"])),
                       max_size=6))
def test_any_dict_is_an_edit_or_one_domain_error_line(d):
    """Property: whatever JSON-like dict is given, parsing yields an edit or one OmniscsError line, never another
    exception; an accepted edit has finite amounts and a non-negative integer track id."""
    try:
        edit = edit_from_dict(d)
    except OmniscsError as exc:
        assert len(str(exc).splitlines()) == 1
        return
    assert isinstance(edit.track_id, int) and not isinstance(edit.track_id, bool) and edit.track_id >= 0
    for name in ("longitudinal", "lateral", "vertical", "yaw_deg", "pitch_deg", "roll_deg"):
        assert math.isfinite(getattr(edit, name, 0.0))
