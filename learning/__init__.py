"""learning: dataset format, virtual observer, models, Algorithm 1, metrics, model bundles.

DESIGN's stable names, loaded on first use (PEP 562): `learning.names` and the command-line
parser stay free of torch and Mitsuba.
"""
from __future__ import annotations

import importlib
from typing import Any

_HOMES = {"Stack": "stack", "StackWriter": "stack", "read_stack": "stack", "write_stack": "stack",
          "make_plan": "stack", "list_stacks": "stack", "update_labels": "stack",
          "VirtualObserver": "observer", "label_stack": "observer", "check_dataset": "check", "Problem": "check",
          "import_lisic": "lisic", "make_synthetic_stack": "synthetic", "load_model": "bundle"}
__all__ = list(_HOMES)


def __getattr__(name: str) -> Any:
    if name not in _HOMES:
        raise AttributeError(f"module 'learning' has no attribute {name!r}")
    return getattr(importlib.import_module(f".{_HOMES[name]}", __name__), name)
