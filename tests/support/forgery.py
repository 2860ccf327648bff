"""Forged decision state for a checkpoint's arrays (the digest is recomputed by whoever
writes them back), and a loop killed at its n-th decision: shared by the forged-evidence
and budget tests and `benchmarks.hardening_loop_state`."""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np


def zero_evidence(arrays: dict[str, np.ndarray]) -> None:
    arrays["evidence"] = np.zeros_like(arrays["evidence"])


def huge_evidence(arrays: dict[str, np.ndarray]) -> None:
    ev = arrays["evidence"].copy()
    ev[:, 0] = np.where(ev[:, 1] > 0, 1e300, 0.0)
    arrays["evidence"] = ev


def tiny_evidence(arrays: dict[str, np.ndarray]) -> None:
    ev = arrays["evidence"].copy()
    ev[:, 0] = ev[:, 0] * 1e-6                   # weights kept: every unit's mean nearly 0
    arrays["evidence"] = ev


def latest_next_decision(arrays: dict[str, np.ndarray]) -> None:
    from learning.inputs.history import last_decided_spp

    decided = last_decided_spp(arrays["history"], arrays["history_block_spp"])
    arrays["next_spp"] = np.where(decided > 0, decided << 20, arrays["next_spp"])


FORGERIES: dict[str, Callable[[dict[str, np.ndarray]], None]] = {
    "evidence zeroed": zero_evidence, "evidence of 1e300": huge_evidence,
    "evidence scaled by 1e-6": tiny_evidence, "next decisions at the latest allowed": latest_next_decision}


def killed_at(n: int) -> Callable[..., Any]:
    """A `PassLoop.judge` that raises RuntimeError("simulated kill") at its n-th call and
    judges as the real one before: a render killed mid-way, its checkpoint left behind."""
    from renderer.live.passloop import PassLoop

    real, calls = PassLoop.judge, {"n": 0}

    def dying(self: Any, ids: Any) -> Any:
        calls["n"] += 1
        if calls["n"] == n:
            raise RuntimeError("simulated kill")
        return real(self, ids)
    return dying
