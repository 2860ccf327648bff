"""The extreme inputs every numeric path on half buffers is tested on (the brief: black,
constant, fireflies, NaN/Inf, tiny and huge values, and an empty batch)."""
from __future__ import annotations

import numpy as np

CASES = ("black", "constant", "fireflies", "nan_inf", "tiny", "huge", "empty")


def extreme_halves(case: str, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Copies of two half-buffer batches [N >= 2, H >= 8, W >= 8, 3] made into `case`."""
    a, b = a.astype(np.float32, copy=True), b.astype(np.float32, copy=True)
    if case == "black":
        a[:], b[:] = 0, 0
    elif case == "constant":
        a[:], b[:] = 0.5, 0.5
    elif case == "fireflies":
        a[:, 3, 5] = 1e30
        b[:, 7, 1] = 3e38
    elif case == "nan_inf":
        a[0, 0, 0] = np.nan
        b[1, 2, 2] = np.inf
        a[1, 4, 4] = -np.inf
    elif case == "tiny":
        a, b = a * np.float32(1e-30), b * np.float32(1e-30)
    elif case == "huge":
        a, b = a * np.float32(1e30), b * np.float32(1e30)
    elif case == "empty":
        a, b = a[:0], b[:0]
    else:
        raise ValueError(f"unknown case {case!r}")
    return a, b
