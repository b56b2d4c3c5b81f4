"""The one reader of untrusted JSON and the guarded Parquet check: hostile input (deep nesting, huge integers,
non-finite numbers, bytes that are not UTF-8, endless streams, FIFOs, folders, junk and foreign Parquet files) is one
OmniscsError line naming the file and what was wrong, never a RecursionError, ValueError, UnicodeDecodeError, a hang
or a pyarrow trace; ordinary JSON reads exactly as ``json.loads`` reads it."""
from __future__ import annotations

import json
import math
import os
import threading

import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from omniscs.errors import OmniscsError, ValidationError
from omniscs.untrusted import (MAX_INT_DIGITS, MAX_JSON_DEPTH, check_parquet_files, check_parquet_schema,
                               loads_json, read_json, read_own_json)


def _one_line(exc: pytest.ExceptionInfo) -> str:
    text = str(exc.value)
    assert "\n" not in text and text
    return text


@pytest.mark.parametrize("text, message", [
    ("[" * 100_000 + "]" * 100_000, f"nested more than {MAX_JSON_DEPTH} deep"),
    ("[" * 100_000, f"nested more than {MAX_JSON_DEPTH} deep"),            # and never closed
    ('{"a":' * 50_000 + "1" + "}" * 50_000, f"nested more than {MAX_JSON_DEPTH} deep"),
    ("1" * 5000, "integer of 5000 digits"),
    ('{"n": -' + "9" * 5000 + "}", "integer of 5000 digits"),
    ('{"x": NaN}', "holds NaN"),
    ("[Infinity]", "holds Infinity"),
    ("[-Infinity]", "holds -Infinity"),
    ("[1e400]", "too large for a float"),
    ("[-1E+400]", "too large for a float"),
    ("[9.99e308]", "too large for a float"),
    ("[1" + "0" * 400 + ".5]", "too large for a float"),
    (b'{"op": "remove\xff"}', "is not UTF-8 text (byte 14 is 0xff)"),
    (b"\xef\xbb\xbf{}", "not valid JSON"),                                 # a byte-order mark
    ("{not json", "not valid JSON"),
    ("", "not valid JSON"),
])
def test_hostile_json_text_is_one_clear_error(text, message):
    with pytest.raises(OmniscsError, match="^the edit list ") as exc:
        loads_json(text, "the edit list")
    assert message in _one_line(exc)


def test_command_line_text_with_undecodable_bytes_is_refused_with_their_offset():
    """Python hands argv bytes that are not UTF-8 over as lone surrogates; the reader names the original byte."""
    argv_text = b'{"op": "\xfe"}'.decode("utf-8", "surrogateescape")
    with pytest.raises(OmniscsError, match=r"byte 8 is 0xfe"):
        loads_json(argv_text, "the edit list")


@pytest.mark.parametrize("text", [
    '{"a": [1, 2.5, -3e-7, "x\\"]]]]", {"b": null, "c": true}], "d": "\\\\"}',
    "[" * MAX_JSON_DEPTH + "]" * MAX_JSON_DEPTH,                            # exactly as deep as allowed
    '["' + "[" * 5000 + '"]',                                                # brackets inside a string do not nest
    '["\\\\\\"' + "[" * 5000 + '"]',                                         # nor after an escaped quote
    "[" + "9" * MAX_INT_DIGITS + "]",
    '["' + "1" * 5000 + '", "e12345", 1e308, 1e-400]',                       # digits in strings, underflow to 0
    "0." + "1" * 5000,                                                       # a long fraction is an ordinary float
])
def test_ordinary_json_reads_as_json_loads_reads_it(text):
    assert loads_json(text, "x") == json.loads(text)


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-10**30, 10**30) | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(alphabet=st.characters(codec="utf-8"), max_size=12)
    | st.sampled_from(['"', "\\", '\\"', "[", "]}", "e999"]),  # what could fool the bracket count or the scan
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4), max_leaves=30)


@settings(max_examples=300, deadline=None)
@given(JSON_VALUES, st.booleans())
def test_any_json_we_could_write_reads_back_exactly_as_json_loads_reads_it(value, ascii_only):
    text = json.dumps(value, ensure_ascii=ascii_only)
    assert loads_json(text, "x") == json.loads(text)


def test_an_escaped_backslash_before_a_quote_closes_the_string():
    """``"\\\\"`` is a string holding one backslash: the brackets after it nest again."""
    with pytest.raises(OmniscsError, match="nested more than"):
        loads_json('["\\\\"' + "[" * 300 + "]" * 300 + "]", "x")


def test_nan_and_infinities_only_where_the_caller_allows_them(tmp_path):
    assert math.isnan(loads_json("NaN", "x", allow_nan=True))
    with pytest.raises(OmniscsError, match="only finite numbers or NaN here"):
        loads_json("[Infinity]", "x", allow_nan=True)
    with pytest.raises(OmniscsError, match="too large for a float"):
        loads_json("[1e999]", "x", allow_nan=True)
    path = tmp_path / "record.json"
    path.write_text(json.dumps({"loss": math.inf, "psnr": math.nan}))
    got = read_own_json(path)
    assert got["loss"] == math.inf and math.isnan(got["psnr"])
    with pytest.raises(OmniscsError, match="holds Infinity"):
        read_json(path)


def test_a_file_error_names_the_file_and_says_what_to_do(tmp_path):
    path = tmp_path / "graph.json"
    path.write_bytes(b"[" * 100_000)
    with pytest.raises(ValidationError) as exc:
        read_json(path, "fit the scene again", error=ValidationError)
    assert _one_line(exc) == f"{path} is nested more than {MAX_JSON_DEPTH} deep; fit the scene again"
    path.write_text("[1, 2]")
    with pytest.raises(OmniscsError, match=r"holds a JSON array, not an object; fit the scene again"):
        read_json(path, "fit the scene again", expect=dict)


def test_endless_streams_folders_fifos_and_missing_files_are_refused_without_reading(tmp_path):
    with pytest.raises(OmniscsError, match="^results file /dev/zero is a device, not a regular file"):
        read_json("/dev/zero", what="results file")
    with pytest.raises(OmniscsError, match="is a folder, not a regular file"):
        read_json(tmp_path)
    with pytest.raises(OmniscsError, match=r"cannot read JSON file .*nope\.json \(No such file"):
        read_json(tmp_path / "nope.json")
    fifo = tmp_path / "results.json"
    os.mkfifo(fifo)
    outcome = []
    reader = threading.Thread(target=lambda: outcome.append(pytest.raises(OmniscsError, read_json, fifo)))
    reader.start()
    reader.join(10)
    try:
        assert not reader.is_alive(), "reading a FIFO with no writer hung"
        assert "is a FIFO (named pipe), not a regular file" in str(outcome[0].value)
    finally:
        if reader.is_alive():  # unblock it: open the FIFO for writing once
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))


def test_a_file_over_the_size_cap_is_refused(tmp_path):
    path = tmp_path / "table.json"
    path.write_text(json.dumps(list(range(1000))))
    with pytest.raises(OmniscsError, match=r"is 4,890 bytes, more than the 1,000 allowed"):
        read_json(path, max_bytes=1000)
    assert read_json(path, max_bytes=10_000) == list(range(1000))


# ----------------------------------------------------------------------------- Parquet
SCHEMA = pa.schema([pa.field("scene_id", pa.string(), nullable=False), pa.field("n", pa.int64())])


def test_junk_truncated_and_foreign_parquet_files_are_refused_by_name(tmp_path):
    good = tmp_path / "good.parquet"
    pq.write_table(pa.table({"scene_id": ["a"], "n": pa.array([1], pa.int32())}), good)
    check_parquet_schema(good, SCHEMA, "catalog file", "move it away", required=("scene_id",))
    older = tmp_path / "older.parquet"  # a file written before a column existed reads it as null
    pq.write_table(pa.table({"scene_id": ["a"]}), older)
    check_parquet_schema(older, SCHEMA, "catalog file", "move it away", required=("scene_id",))

    cases = {
        "junk": (b"this is not parquet at all, no magic here", "is not a Parquet file"),
        "truncated": (good.read_bytes()[: good.stat().st_size // 2], "is not a Parquet file"),
        "empty": (b"", "is not a Parquet file"),
        "bad footer": (b"PAR1" + b"\x00" * 64 + b"PAR1", "is a damaged Parquet file"),
    }
    for name, (data, message) in cases.items():
        path = tmp_path / f"{name}.parquet"
        path.write_bytes(data)
        with pytest.raises(OmniscsError, match=f"^catalog file {path} {message}") as exc:
            check_parquet_schema(path, SCHEMA, "catalog file", "move it away", required=("scene_id",))
        assert _one_line(exc).endswith("; move it away")
    foreign = {
        "extra column": pa.table({"scene_id": ["a"], "password": ["x"]}),
        "other kind": pa.table({"scene_id": [1.5]}),
        "no key": pa.table({"n": [1]}),
    }
    for name, table in foreign.items():
        path = tmp_path / f"{name}.parquet"
        pq.write_table(table, path)
        with pytest.raises(OmniscsError, match="is not one of ours"):
            check_parquet_schema(path, SCHEMA, "catalog file", "move it away", required=("scene_id",))


def test_a_checked_file_replaced_by_junk_is_checked_again(tmp_path):
    path = tmp_path / "rows.parquet"
    pq.write_table(pa.table({"scene_id": ["a"]}), path)
    check_parquet_files([path], SCHEMA, "catalog file", "move it away", required=("scene_id",))
    junk = tmp_path / ".junk"
    junk.write_bytes(b"PAR1 not really PAR1")
    os.replace(junk, path)  # what a writer's atomic rename does: a new file under the same name
    with pytest.raises(OmniscsError, match="is not a Parquet file|is a damaged Parquet file"):
        check_parquet_files([path], SCHEMA, "catalog file", "move it away", required=("scene_id",))
