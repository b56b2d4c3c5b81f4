"""Small checks shared by everything that reads JSON a user or a crash could have damaged (checkpoints, stores,
dataset tables, presets, requests): JSON's numbers are Python's, so ``True`` is an int and ``NaN`` a float; these
predicates say what a field really holds, and ``read_json`` turns any unreadable file into one domain error (through
``omniscs.untrusted``, the one reader of untrusted JSON)."""
from __future__ import annotations

import math
import numbers
import os
from pathlib import Path

from omniscs.errors import OmniscsError
from omniscs.untrusted import read_own_json


def is_int(value) -> bool:
    """An integer, not a bool."""
    return isinstance(value, int) and not isinstance(value, bool)


def is_real(value) -> bool:
    """An int or a float, not a bool (NaN and infinities included)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def is_finite(value) -> bool:
    """A real number that is neither NaN nor infinite."""
    return is_real(value) and math.isfinite(value)


#: Most torch threads a command may ask for: a few per core (more only thrash; 10,000 took the load to 300).
MAX_THREADS = 4 * (os.cpu_count() or 1)
#: Most optimiser steps a command may ask for (the accurate preset takes 5,000).
MAX_ITERATIONS = 1_000_000
#: Largest seed a procedural world or a sampler takes (32 bits: what every tool that records seeds can hold).
MAX_SEED = 2**32 - 1


def check_seed(value, what: str = "seed") -> int:
    """``value`` as a seed in [0, MAX_SEED]; anything else (a bool, a float, a negative or larger number) is one
    OmniscsError naming ``what``."""
    if not isinstance(value, numbers.Integral) or isinstance(value, bool) or not 0 <= value <= MAX_SEED:
        raise OmniscsError(f"{what} must be a whole number from 0 to {MAX_SEED}; got {value!r}")
    return int(value)


def read_json(path: Path, damaged: str):
    """The JSON value in ``path``, one of our own artifacts (a checkpoint, a card), read as untrusted
    (``omniscs.untrusted.read_json``: a regular file, size, depth and digit caps, strict UTF-8); NaN and infinities
    are read, as our writers may record them. Any problem is one OmniscsError naming the file (``damaged`` says
    what that means and what to do)."""
    return read_own_json(path, damaged)
