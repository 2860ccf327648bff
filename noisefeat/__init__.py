"""noisefeat: sub-image -> 26 noise features (12 conv layers + 1 wavelet layer), torch on CPU.

Names are loaded on first use (PEP 562), so that `noisefeat.bounds` and the command-line
parser do not import torch. The display transform is `noisefeat.display.display`: the
package attribute `display` is its module, as for every sub-module.
"""
from __future__ import annotations

import importlib
from typing import Any

_HOMES = {"FeatureBase": "base", "FEATURE_NAMES": "base", "N_FEATURES": "base", "split_blocks": "blocks",
          "merge_blocks": "blocks", "extract_features": "extract",
          "default_base": "extract"}
__all__ = list(_HOMES)


def __getattr__(name: str) -> Any:
    if name not in _HOMES:
        raise AttributeError(f"module 'noisefeat' has no attribute {name!r}")
    return getattr(importlib.import_module(f".{_HOMES[name]}", __name__), name)
