"""The registry of the weights shipped with the package: one entry per model (its files with their sha256 and size,
the command, seed and data that reproduce it, its training record), where they live, and the check that a default
model is loaded from exactly the files that were registered.

The entries are data (``registry.json`` beside this file), rewritten only by ``register`` after a trainer installs
new weights (``omniscs pretrained train NAME``). A user's own weights (a folder passed to a loader) are not checked
against the registry: only a folder that *is* a registered one is.
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from omniscs.errors import OmniscsError, ValidationError

#: Where the shipped weights live: one folder per entry, named by the entry.
WEIGHTS_ROOT = Path(__file__).resolve().parent / "weights"
#: The entries (data; ``register`` rewrites a file's hash and size there).
REGISTRY_FILE = Path(__file__).resolve().parent / "registry.json"
#: How many leading hex digits of a hash errors and listings show.
PREFIX = 12


@dataclass(frozen=True)
class ShippedFile:
    """One file of a shipped model."""

    name: str
    """File name inside the model's folder."""
    sha256: str
    """Hex digest of the file's bytes as registered."""
    size: int
    """Size in bytes as registered."""


@dataclass(frozen=True)
class Shipped:
    """One shipped model: what it is, its files, and how to make it again."""

    name: str
    """Registry name (also its folder under ``WEIGHTS_ROOT`` and the argument of ``omniscs pretrained``)."""
    title: str
    """What the model is, in a few words."""
    loader: str
    """The library function that loads it by default (dotted path)."""
    files: tuple[ShippedFile, ...]
    """Every file the loader reads, plus the training record and any README (all hash-checked)."""
    command: str
    """The command that reproduces the weights on this code."""
    seed: int
    """The seed of that command's training run."""
    data: str
    """The data it trains on (which procedural worlds or logs, how many)."""
    record: str = "training.json"
    """The training record (config, data, loss curve, evaluation, machine) beside the weights."""

    @property
    def folder(self) -> Path:
        """The folder that holds the files."""
        return WEIGHTS_ROOT / self.name


def _parse(raw: dict) -> dict[str, Shipped]:
    entries = {}
    for item in raw["models"]:
        files = tuple(ShippedFile(f["name"], f["sha256"], int(f["size"])) for f in item["files"])
        entries[item["name"]] = Shipped(item["name"], item["title"], item["loader"], files, item["command"],
                                        int(item["seed"]), item["data"], item.get("record", "training.json"))
    return entries


@lru_cache(maxsize=1)
def entries() -> dict[str, Shipped]:
    """Every registered model by name (read once per process)."""
    try:
        return _parse(json.loads(REGISTRY_FILE.read_text()))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise OmniscsError(f"the registry of shipped weights {REGISTRY_FILE} is missing or damaged ({exc}); "
                           "reinstall omniscs") from None


def entry(name: str) -> Shipped:
    """The entry called ``name``; an OmniscsError listing the names otherwise."""
    known = entries()
    if name not in known:
        raise OmniscsError(f"no shipped model called {name!r}; choose one of {', '.join(known)}")
    return known[name]


def folder(name: str) -> Path:
    """The folder of the shipped model ``name`` (not verified: ``verified_folder`` checks it)."""
    return WEIGHTS_ROOT / name


#: sha256 by (resolved path, size, mtime in ns): each file is hashed once per process unless it changes.
_HASHES: dict[tuple[str, int, int], str] = {}


def file_sha256(path: Path) -> str:
    """The hex sha256 of ``path``, cached by path, size and modification time."""
    stat = path.stat()
    key = (str(path.resolve()), stat.st_size, stat.st_mtime_ns)
    if key not in _HASHES:
        h = hashlib.sha256()
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        _HASHES[key] = h.hexdigest()
    return _HASHES[key]


def mismatches(model: Shipped, where: Path | None = None) -> list[str]:
    """One line per file of ``model`` (in ``where``, default its folder) that is missing or differs from the
    registry; [] when every file is as registered."""
    where = model.folder if where is None else Path(where)
    bad = []
    for f in model.files:
        path = where / f.name
        if not path.is_file():
            bad.append(f"{path} is missing")
            continue
        found = file_sha256(path)
        if found != f.sha256:
            bad.append(f"{path} has sha256 {found[:PREFIX]}…, the registry expects {f.sha256[:PREFIX]}…")
    return bad


def restore_hint(model: Shipped) -> str:
    return (f"reinstall omniscs (pip install --force-reinstall omniscs, or git checkout the file), or make the "
            f"weights again with `{model.command}`")


def verify(name: str, where: Path | None = None) -> Path:
    """The folder of shipped model ``name`` after checking every file's hash; one OmniscsError naming the first
    changed or missing file, the expected and found hash prefixes and how to restore it otherwise."""
    model = entry(name)
    where = model.folder if where is None else Path(where)
    bad = mismatches(model, where)
    if bad:
        more = f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""
        raise OmniscsError(f"the shipped {model.title} weights were changed: {bad[0]}{more}; "
                           f"{restore_hint(model)}")
    return where


def shipped_name(path: str | os.PathLike) -> str | None:
    """The registry name when ``path`` is a registered model's folder, else None (a user's own folder)."""
    try:
        resolved = Path(path).resolve()
    except OSError:
        return None
    if resolved.parent != WEIGHTS_ROOT:
        return None
    return resolved.name if resolved.name in entries() else None


def verified_folder(path: str | os.PathLike) -> Path:
    """``path`` itself; when it is a registered model's folder, its files are hash-checked first (``verify``)."""
    name = shipped_name(path)
    if name is not None:
        verify(name)
    return Path(path)


def register(name: str) -> Shipped:
    """Record the current hash and size of every file of ``name`` in ``registry.json`` (after a trainer installed
    new weights into its folder); the command, seed and data stay as they are."""
    from omniscs.storage import atomic_write_text

    raw = json.loads(REGISTRY_FILE.read_text())
    for item in raw["models"]:
        if item["name"] != name:
            continue
        where = WEIGHTS_ROOT / name
        for f in item["files"]:
            path = where / f["name"]
            if not path.is_file():
                raise OmniscsError(f"cannot register {name}: {path} is missing; run `{item['command']}` first")
            f["sha256"], f["size"] = file_sha256(path), path.stat().st_size
        break
    else:
        raise OmniscsError(f"no shipped model called {name!r}; choose one of {', '.join(entries())}")
    atomic_write_text(REGISTRY_FILE, json.dumps(raw, indent=1) + "\n")
    entries.cache_clear()
    return entry(name)


def package_data_patterns() -> list[str]:
    """The package-data globs (relative to the ``omniscs.pretrained`` package) that a wheel needs to hold every
    registered file and the registry itself."""
    return ["registry.json"] + sorted({f"weights/{m.name}/{f.name}" for m in entries().values() for f in m.files})


def load(name: str):
    """The shipped model ``name`` loaded by its default loader (``Shipped.loader``) from its verified folder."""
    import importlib

    model = entry(name)
    module, _, function = model.loader.rpartition(".")
    return getattr(importlib.import_module(module), function)(verify(name))


def network_with_weights(network, state: dict, folder: Path, config_name: str):
    """``network`` (a torch module) holding ``state``, in eval mode; weights that do not fit it are one clear error
    naming the folder and the config file that describes the network."""
    try:
        network.load_state_dict(state)
    except RuntimeError as e:
        raise ValidationError(f"{folder}: the weights do not fit the network of {config_name} ({e})") from e
    return network.eval()
