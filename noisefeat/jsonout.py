"""The one JSON encoder of the project: manifests, report.json and `--json` output all go
through `json_default`, so a numpy value or a path is written the same way everywhere."""
from __future__ import annotations

import os
from typing import Any


def json_default(o: Any) -> Any:
    """`json.dumps` default: numpy scalars and arrays as plain values, paths as strings;
    anything else is a TypeError naming its type (never a silent repr). NumPy is imported
    here, when a value needs it: the command line's `--json` path imports nothing heavy."""
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, os.PathLike):
        return os.fspath(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
