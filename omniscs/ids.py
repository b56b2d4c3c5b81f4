"""The one rule for ids that become file or folder names (scene ids, run ids, model and variant names, writer
names): letters, digits, '.', '_' and '-', starting with a letter or digit, at most 128 characters. An id that
breaks it (``../x``, ``a/b``, an empty string) is refused before any path is built from it."""
from __future__ import annotations

import re

from omniscs.errors import OmniscsError

#: Longest id accepted (file systems allow 255 bytes per name; prefixes and suffixes are added to ids).
MAX_ID_LENGTH = 128

_SAFE_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")


def is_safe_id(value) -> bool:
    """True when ``value`` is a string that can name a file or folder on its own."""
    return (isinstance(value, str) and len(value) <= MAX_ID_LENGTH and _SAFE_ID.fullmatch(value) is not None
            and ".." not in value)


def check_id(kind: str, value) -> str:
    """``value`` when it is a safe id (see the module docstring), else one OmniscsError naming ``kind``."""
    if not is_safe_id(value):
        raise OmniscsError(f"{kind} {value!r} is not a safe id: use 1 to {MAX_ID_LENGTH} letters, digits, '.', "
                           "'_' or '-', starting with a letter or digit, without '..'")
    return value
