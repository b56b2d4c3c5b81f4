"""The docs generator (docs/gen_results.py) imported by path: it lives in the site's source folder, not a package."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def load_generator():
    """docs/gen_results.py as a module."""
    spec = importlib.util.spec_from_file_location("omniscs_docs_gen_results", REPO / "docs" / "gen_results.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the file runs
    spec.loader.exec_module(module)
    return module
