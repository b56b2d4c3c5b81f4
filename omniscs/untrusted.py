"""Readers for what a user or another process hands us (JSON files and text, Parquet files): each reads only a
regular file, within a size cap, and turns anything hostile or damaged into one OmniscsError line that names the file,
says what was wrong and what to do; no RecursionError, ValueError, UnicodeDecodeError or pyarrow trace escapes."""
from __future__ import annotations

import json
import math
import os
import stat
from pathlib import Path

import numpy as np

from omniscs.errors import OmniscsError

#: Default size cap of a JSON file (bytes): far above any manifest, spec, card or results file we write; readers of
#: bigger real data (a nuScenes table of a full dataroot: hundreds of MB) pass their own.
MAX_JSON_BYTES = 64 * 2**20
#: Size cap for a nuScenes table (sample_annotation.json of the full trainval split is about 500 MB).
MAX_TABLE_BYTES = 2 * 2**30
#: Deepest nesting of arrays and objects a JSON document may have (ours are under 10 deep; Python's parser recurses
#: per level and stops near 1,000 with a RecursionError).
MAX_JSON_DEPTH = 256
#: Most digits an integer may have (int64 has 19; Python refuses to parse more than 4,300 with a ValueError).
MAX_INT_DIGITS = 100

# Digits become '0', an exponent's 'e' and '+' stay, everything else a space: a long run of digits or an exponent of
# three digits is then a plain substring search.
_NUMBER_SHAPES = bytes(ord("0") if chr(b).isdigit() and b < 128 else ord("e") if b in b"eE" else b if b == ord("+")
                       else ord(" ") for b in range(256))


class _Refused(Exception):
    """A problem found in the JSON (raised inside the parse, turned into an OmniscsError that names the file)."""


def _string_quotes(arr: np.ndarray, data: bytes) -> np.ndarray:
    """Positions of the quotes that open or close a JSON string in ``arr`` (= ``data`` as uint8): a quote after
    an odd run of backslashes is part of a string."""
    quote = arr == ord('"')
    if b'\\"' in data:  # rare in real data: walk back over each backslash run before a quote
        for q in np.flatnonzero(quote[1:] & (arr[:-1] == ord("\\"))) + 1:
            run = 0
            while q - run - 1 >= 0 and arr[q - run - 1] == ord("\\"):
                run += 1
            quote[q] = run % 2 == 0
    return np.flatnonzero(quote)


def _outside_strings(data: bytes) -> bytes:
    """The bytes of ``data`` (JSON) outside its strings, found with array passes (no Python loop per byte: a real
    nuScenes table is hundreds of MB)."""
    arr = np.frombuffer(data, dtype=np.uint8)
    toggles = np.zeros(arr.size, dtype=np.uint8)
    toggles[_string_quotes(arr, data)] = 1
    inside = np.bitwise_xor.accumulate(toggles)  # 1 from an opening quote up to (not including) its closing one
    return arr[inside == 0].tobytes()


_BRACKET_STEP = np.zeros(256, dtype=np.int8)
_BRACKET_STEP[[ord("["), ord("{")]] = 1
_BRACKET_STEP[[ord("]"), ord("}")]] = -1


# Every byte but brackets and quotes, deleted with bytes.translate (C speed).
_NOT_STRUCTURE = bytes(b for b in range(256) if b not in b'[]{}"')


def _depth(data: bytes) -> int:
    """Deepest nesting of arrays and objects in ``data`` (JSON), counted without recursion and without a Python
    loop per byte: escaped backslashes and quotes are dropped first (pairing a run of backslashes from its start is
    how JSON reads it), then brackets after an odd number of quotes lie inside a string and do not count."""
    if b"\\" in data:
        data = data.replace(b"\\\\", b"").replace(b'\\"', b"")
    structure = np.frombuffer(data.translate(None, _NOT_STRUCTURE), dtype=np.uint8)
    in_string = np.bitwise_xor.accumulate((structure == ord('"')).view(np.uint8))
    steps = _BRACKET_STEP[structure][in_string == 0]
    return int(np.cumsum(steps, dtype=np.int64).max(initial=0))


def _numbers_hooks(allow_inf: bool, max_int_digits: int) -> dict:
    """``json.loads`` hooks that refuse overlong integers and (unless ``allow_inf``) numbers that overflow a
    float."""
    def parse_int(text: str) -> int:
        if len(text.lstrip("-")) > max_int_digits:
            raise _Refused(f"holds an integer of {len(text.lstrip('-'))} digits (at most {max_int_digits})")
        return int(text)

    def parse_float(text: str) -> float:
        value = float(text)
        if not allow_inf and not math.isfinite(value):
            raise _Refused(f"holds a number too large for a float ({text[:40]}{'...' if len(text) > 40 else ''})")
        return value

    return {"parse_int": parse_int, "parse_float": parse_float}


def _parse(data: bytes, allow_nan: bool, allow_inf: bool, max_depth: int, max_int_digits: int):
    """The JSON value in ``data``; a problem is ``_Refused`` (with what was wrong, for a message)."""
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise _Refused(f"is not UTF-8 text (byte {exc.start} is 0x{data[exc.start]:02x})") from None
    may_nest = data.count(b"[") + data.count(b"{") > max_depth
    shapes = data.translate(_NUMBER_SHAPES)
    may_refuse = b"0" * (max_int_digits + 1) in shapes or b"e000" in shapes or b"e+000" in shapes
    if may_nest and _depth(data) > max_depth:
        raise _Refused(f"is nested more than {max_depth} deep")

    def parse_constant(name: str) -> float:
        if not (allow_nan if name == "NaN" else allow_inf):
            allowed = "finite numbers or NaN" if allow_nan else "finite numbers"
            raise _Refused(f"holds {name}, which is not a number JSON allows (only {allowed} here)")
        return float(name)

    hooks = {}
    # The number hooks cost a Python call per number: used only when a number could be refused (a long run of
    # digits, or an exponent of three digits or more), so big tables of ordinary numbers parse at C speed.
    if may_refuse:  # look again outside strings (a token such as "e4120..." is no exponent)
        shapes = _outside_strings(data).translate(_NUMBER_SHAPES)
        if b"0" * (max_int_digits + 1) in shapes or b"e000" in shapes or b"e+000" in shapes:
            hooks = _numbers_hooks(allow_inf, max_int_digits)
    try:
        return json.loads(text, parse_constant=parse_constant, **hooks)
    except json.JSONDecodeError as exc:
        raise _Refused(f"is not valid JSON ({exc})") from None
    except RecursionError:  # cannot happen below max_depth; kept so that no limit ever shows as a traceback
        raise _Refused(f"is nested too deep (at most {max_depth})") from None
    except ValueError as exc:  # e.g. Python's own limit on integer digits
        raise _Refused(f"is not valid JSON ({exc})") from None


def read_regular_file(path: str | os.PathLike, max_bytes: int, what: str, hint: str,
                      error: type[OmniscsError] = OmniscsError) -> bytes:
    """The bytes of ``path``, which must be a regular file of at most ``max_bytes``; a FIFO, a device (an endless
    stream such as /dev/zero), a folder, a missing or unreadable file is one ``error`` (an OmniscsError) naming
    ``what`` and the file (``hint`` says what to do). The file is opened without blocking, so a FIFO with no writer
    never hangs."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        raise error(f"cannot read {what} {path} ({exc.strerror or exc}); {hint}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            kind = ("a folder" if stat.S_ISDIR(st.st_mode) else "a FIFO (named pipe)" if stat.S_ISFIFO(st.st_mode)
                    else "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode)
                    else "a socket" if stat.S_ISSOCK(st.st_mode) else "not a regular file")
            raise error(f"{what} {path} is {kind}, not a regular file; give a file")
        if st.st_size > max_bytes:
            raise error(f"{what} {path} is {st.st_size:,} bytes, more than the {max_bytes:,} allowed; {hint}")
        chunks, total = [], 0
        while True:  # a file that grows while we read stops at the cap too
            chunk = os.read(fd, min(1 << 24, max_bytes + 1 - total))
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
            if total > max_bytes:
                raise error(f"{what} {path} is more than the {max_bytes:,} bytes allowed; {hint}")
        return b"".join(chunks)
    except OSError as exc:
        raise error(f"cannot read {what} {path} ({exc.strerror or exc}); {hint}") from None
    finally:
        os.close(fd)


def read_json(path: str | os.PathLike, damaged: str = "fix or replace the file", *, expect: type | None = None,
              max_bytes: int = MAX_JSON_BYTES, allow_nan: bool = False, allow_inf: bool = False,
              max_depth: int = MAX_JSON_DEPTH, max_int_digits: int = MAX_INT_DIGITS, what: str = "JSON file",
              error: type[OmniscsError] = OmniscsError):
    """The JSON value in ``path`` (a regular file of at most ``max_bytes``), read as untrusted: strict UTF-8, nested
    at most ``max_depth``, integers of at most ``max_int_digits`` digits, only finite numbers (``allow_nan``: NaN too,
    e.g. the nuScenes results format's "no velocity"; ``allow_inf``: +-Infinity and numbers that overflow a float, as
    Python's own json writes and reads them), and of type ``expect`` when given.
    Anything else is one ``error`` (OmniscsError or a subclass) naming the file and what was wrong; ``damaged`` says
    what that means and what to do (e.g. "the dataset card is damaged; build the dataset again")."""
    data = read_regular_file(path, max_bytes, what, damaged, error)
    try:
        value = _parse(data, allow_nan, allow_inf, max_depth, max_int_digits)
    except _Refused as exc:
        raise error(f"{path} {exc}; {damaged}") from None
    if expect is not None and not isinstance(value, expect):
        raise error(f"{path} holds a JSON {_json_type(value)}, not {_json_type_name(expect)}; {damaged}")
    return value


def read_own_json(path: str | os.PathLike, damaged: str = "fix or replace the file", **options):
    """A JSON file one of our stages wrote (a checkpoint's record, a dataset card, a plan, a stage's rows), read
    as ``read_json`` reads untrusted files (someone may have damaged or replaced it) except that NaN and
    infinities are kept: our writers record them (a diverged loss, a PSNR without a reference)."""
    return read_json(path, damaged, allow_nan=True, allow_inf=True, **options)


def loads_json(text: str | bytes | bytearray, what: str, hint: str = "", *, expect: type | None = None,
               max_bytes: int = MAX_JSON_BYTES, allow_nan: bool = False, allow_inf: bool = False,
               max_depth: int = MAX_JSON_DEPTH, max_int_digits: int = MAX_INT_DIGITS):
    """JSON given as text (on the command line, in a request): the same checks as ``read_json``; an error names
    ``what`` (e.g. "the edit list") and ends with ``hint`` when given."""
    if isinstance(text, str):
        try:  # text from the command line carries undecodable bytes as lone surrogates: get the bytes back
            data = text.encode("utf-8", "surrogateescape")
        except UnicodeEncodeError:
            data = text.encode("utf-8", "surrogatepass")  # any other lone surrogate: invalid UTF-8, refused below
    else:
        data = bytes(text)
    tail = f"; {hint}" if hint else ""
    if len(data) > max_bytes:
        raise OmniscsError(f"{what} is {len(data):,} bytes, more than the {max_bytes:,} allowed{tail}")
    try:
        value = _parse(data, allow_nan, allow_inf, max_depth, max_int_digits)
    except _Refused as exc:
        raise OmniscsError(f"{what} {exc}{tail}") from None
    if expect is not None and not isinstance(value, expect):
        raise OmniscsError(f"{what} is a JSON {_json_type(value)}, not {_json_type_name(expect)}{tail}")
    return value


def _json_type(value) -> str:
    return {dict: "object", list: "array", str: "string", bool: "boolean", type(None): "null"}.get(
        type(value), "number")


def _json_type_name(expect) -> str:
    kinds = expect if isinstance(expect, tuple) else (expect,)
    names = {dict: "an object", list: "an array", str: "a string"}
    return " or ".join(names.get(k, k.__name__) for k in kinds)


# ----------------------------------------------------------------------------- Parquet
_PARQUET_MAGIC = b"PAR1"


def parquet_schema(path: str | os.PathLike, what: str, hint: str):
    """The Arrow schema of the Parquet file ``path`` (a regular file that starts and ends with Parquet's magic and
    whose footer reads); junk, a truncated file, a folder or a device is one OmniscsError naming ``what`` and the
    file, with ``hint`` saying what to do."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = Path(path)
    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):
            raise OmniscsError(f"{what} {path} is not a regular file; {hint}")
        with open(path, "rb") as f:
            head = f.read(4)
            f.seek(max(st.st_size - 4, 0))
            tail = f.read(4)
    except OSError as exc:
        raise OmniscsError(f"cannot read {what} {path} ({exc.strerror or exc}); {hint}") from None
    if st.st_size < 12 or head != _PARQUET_MAGIC or tail != _PARQUET_MAGIC:
        raise OmniscsError(f"{what} {path} is not a Parquet file (junk or truncated: no Parquet header and "
                           f"footer); {hint}")
    try:
        return pq.read_schema(path)
    except (pa.ArrowException, OSError, ValueError) as exc:
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise OmniscsError(f"{what} {path} is a damaged Parquet file ({first}); {hint}") from None


def _kind(t) -> str:
    """A coarse kind of an Arrow type: files written by older versions may differ in width (int32 vs int64) or
    string flavour (large_string), never in kind."""
    import pyarrow as pa

    if pa.types.is_null(t):
        return "null"
    if pa.types.is_boolean(t):
        return "bool"
    if pa.types.is_integer(t):
        return "int"
    if pa.types.is_floating(t):
        return "float"
    if pa.types.is_string(t) or pa.types.is_large_string(t):
        return "string"
    if pa.types.is_list(t) or pa.types.is_large_list(t):
        return f"list<{_kind(t.value_type)}>"
    return str(t)


def check_parquet_schema(path: str | os.PathLike, expected, what: str, hint: str,
                         required: tuple[str, ...] = ()) -> None:
    """Refuse (one OmniscsError naming the file) a Parquet file that is junk, truncated, or foreign: a column that
    ``expected`` (a pyarrow schema) does not declare, a declared column of another kind of type, or one of
    ``required`` missing. A file older than a column may lack it (the column then reads as null)."""
    schema = parquet_schema(path, what, hint)
    declared = {f.name: f.type for f in expected}
    foreign = [n for n in schema.names if n not in declared]
    if foreign:
        raise OmniscsError(f"{what} {path} is not one of ours: it has column(s) {foreign[:5]} that the table does "
                           f"not declare; {hint}")
    for field in schema:
        if _kind(field.type) not in ("null", _kind(declared[field.name])):
            raise OmniscsError(f"{what} {path} is not one of ours: column {field.name!r} is {field.type}, the table "
                               f"declares {declared[field.name]}; {hint}")
    missing = [n for n in required if n not in schema.names]
    if missing or not schema.names:
        raise OmniscsError(f"{what} {path} is not one of ours: it lacks column(s) {missing or list(declared)[:5]}; "
                           f"{hint}")


_CHECKED: set[tuple] = set()


def check_parquet_files(files, expected, what: str, hint: str, required: tuple[str, ...] = ()) -> None:
    """``check_parquet_schema`` for each of ``files``; a file already checked against the same schema in this
    process (same path, size, modification time and inode) is not read again, so repeated queries over a large
    catalog stay cheap."""
    tag = expected.to_string()
    for path in files:
        try:
            st = os.stat(path)
            key = (tag, str(path), st.st_size, st.st_mtime_ns, st.st_ino)
        except OSError:
            key = None
        if key is not None and key in _CHECKED:
            continue
        check_parquet_schema(path, expected, what, hint, required)
        if key is not None:
            if len(_CHECKED) > 100_000:
                _CHECKED.clear()
            _CHECKED.add(key)
