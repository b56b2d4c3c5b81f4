"""Ways to damage files on disk for the bad-input tests (stores, dataset tables, checkpoints), and the file list
that shows a failed call left nothing behind."""
from __future__ import annotations

from pathlib import Path

import pyarrow as pa


def files_under(root: Path) -> list[str]:
    """Every file and folder under ``root``, relative and sorted."""
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def write(name: str, data: bytes):
    """Damage: file ``name`` of a folder replaced by ``data``."""
    return lambda folder: (folder / name).write_bytes(data)


def cut(name: str, fraction: float = 0.5):
    """Damage: file ``name`` of a folder cut to ``fraction`` of its bytes."""
    def damage(folder: Path):
        data = (folder / name).read_bytes()
        (folder / name).write_bytes(data[: int(len(data) * fraction)])
    return damage


def set_column(name: str, values, type_=None):
    """A table change: column ``name`` replaced by ``values`` (or ``values(old list)``), as ``type_``."""
    def change(t: pa.Table) -> pa.Table:
        i = t.column_names.index(name)
        vals = values(t.column(name).to_pylist()) if callable(values) else values
        arr = pa.array(vals, type=type_)
        return t.set_column(i, pa.field(name, arr.type), arr)
    return change
