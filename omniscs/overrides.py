"""One way to change a named preset: ``replace_checked`` applies field overrides to a frozen config dataclass and
refuses, with one line, an unknown field, a value of another type than the field's default (a bool for an int,
a string for a number), a number that is NaN or infinite, a negative count, or a zero where at least one is
needed (threads, iterations, steps, worlds, batch size)."""
from __future__ import annotations

import dataclasses
import math

from omniscs.checks import is_int, is_real
from omniscs.errors import OmniscsError

#: Integer fields that need at least 1 (a 0 would silently do nothing, or make torch pick a thread count).
AT_LEAST_ONE = frozenset({"torch_threads", "iterations", "fit_iterations", "steps", "n_worlds", "batch_size"})


def replace_checked(kind: str, base, overrides: dict):
    """``dataclasses.replace(base, **overrides)`` after checking every override (see the module docstring)."""
    names = {f.name for f in dataclasses.fields(base) if f.init}
    for name, value in overrides.items():
        if name not in names:
            raise OmniscsError(f"unknown {kind} setting {name!r}; settings: {sorted(names)}")
        default = getattr(base, name)
        if isinstance(default, bool):
            ok = isinstance(value, bool)
        elif isinstance(default, int):
            ok = is_int(value)
            if ok and (value < 0 or (name in AT_LEAST_ONE and value < 1)):
                raise OmniscsError(f"{kind} setting {name} must be at least {1 if name in AT_LEAST_ONE else 0}; "
                                   f"got {value}")
        elif isinstance(default, float):
            ok = is_real(value)
            if ok and not math.isfinite(value):
                raise OmniscsError(f"{kind} setting {name} must be a finite number; got {value}")
        elif isinstance(default, str):
            ok = isinstance(value, str)
        else:
            ok = True  # nested configs and tuples: their own constructors check them
        if not ok:
            raise OmniscsError(f"{kind} setting {name} must be a {type(default).__name__}; got {value!r}")
    try:
        return dataclasses.replace(base, **overrides)
    except (TypeError, ValueError) as exc:
        raise OmniscsError(f"bad {kind} setting: {exc}") from None
