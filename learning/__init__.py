"""learning: dataset format, virtual observer, models, Algorithm 1, metrics, model bundles.

Sub-packages by job, each importing only those before it: `data` (the stack format, EXR,
the virtual observer, checks and imports), `inputs` (what a model sees of a block: half
buffers, feature tables), `models` (estimators, Algorithm 1, transfer baselines, bundles),
`evaluation` (metrics, the protocol on held-out scenes, calibration of the knobs),
`training` (train one model; train many and compare). Beneath them all: `stoprule`, the
one rule that turns a score into a verdict, and `names`, the choices the command line offers.

DESIGN's stable names, loaded on first use (PEP 562): `learning.names` and the command-line
parser stay free of torch and Mitsuba.
"""
from __future__ import annotations

import importlib
from typing import Any

_HOMES = {**dict.fromkeys(("Stack", "read_stack"), "data.stack"), "list_stacks": "data.dataset_dir",
          **dict.fromkeys(("StackWriter", "write_stack", "make_plan", "update_labels"), "data.stack_write"),
          "VirtualObserver": "data.observer", "label_stack": "data.observer",
          "check_dataset": "data.check", "Problem": "data.check", "import_lisic": "data.lisic",
          "make_synthetic_stack": "data.synthetic", "load_model": "models.bundle"}
__all__ = list(_HOMES)


def __getattr__(name: str) -> Any:
    if name not in _HOMES:
        raise AttributeError(f"module 'learning' has no attribute {name!r}")
    return getattr(importlib.import_module(f".{_HOMES[name]}", __name__), name)
