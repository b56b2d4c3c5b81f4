"""The weights shipped with the package, in one registry (``registry``), and the trainers that make them
(``omniscs.training``, imported on demand: they pull in the procedural world)."""
from omniscs.pretrained.registry import (
    Shipped,
    ShippedFile,
    entries,
    entry,
    folder,
    load,
    mismatches,
    register,
    verified_folder,
    verify,
)

__all__ = ["Shipped", "ShippedFile", "entries", "entry", "folder", "load", "mismatches", "register", "verified_folder",
           "verify"]
