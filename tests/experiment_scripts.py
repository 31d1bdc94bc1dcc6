"""Loads a script of experiments/ as a module, for the tests of its functions."""

from __future__ import annotations

import importlib.util
import sys
import types
from pathlib import Path

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"


def load_experiment(path: str, name: str | None = None) -> types.ModuleType:
    """A fresh module of `experiments/<path>` (e.g. "bench_vs_torch.py", "gpu/paper_scale.py"),
    named `name` (default: the file's stem). It is registered in `sys.modules` before it runs:
    dataclasses resolve their annotations through their module there. The script's folder leads
    `sys.path` while it runs, as when Python runs it, for its imports of sibling scripts."""
    file = EXPERIMENTS / path
    spec = importlib.util.spec_from_file_location(name or file.stem, file)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    sys.path.insert(0, str(file.parent))
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(file.parent))
    return module
