"""The arguments of `renderer.render` / `run_adaptive`, checked one by one before anything
else looks at them, each error naming its own parameter.

Why: settings were combined (min_spp clipped to max_spp) before their types were checked,
so `max_spp=-1` was reported as "min_spp must be a positive integer", `'16'` raised a
TypeError from a comparison and `10**48` seconds an OverflowError. Here strings, bools,
huge numbers and wrong types all get the same one-line ValueError as any other bad value.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from .settings import MAX_SPP, MAX_TIME_LIMIT


def check_count(name: str, value: Any, optional: bool = True) -> None:
    """A whole number of samples per pixel in [1, MAX_SPP] (None passes when optional)."""
    if value is None and optional:
        return
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 1 <= value <= MAX_SPP:
        raise ValueError(f"{name} must be a positive integer, at most {MAX_SPP}, got {_shown(value)}")


def _check_positive(name: str, value: Any, most: float, unit: str) -> None:
    """None, or a finite number in (0, most]; else the one-line error naming `name`."""
    if value is None:
        return
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not 0 < value <= most or (isinstance(value, float) and not math.isfinite(value)):
        shown = f"{most:g}" if isinstance(most, float) else str(most)
        raise ValueError(f"{name} must be a positive number of {unit}, at most {shown}, got {_shown(value)}")


def check_seconds(name: str, value: Any) -> None:
    """None, or a number of seconds in (0, MAX_TIME_LIMIT]."""
    _check_positive(name, value, MAX_TIME_LIMIT, "seconds")


def check_spp_budget(value: Any) -> None:
    """None, or a positive number of samples per pixel up to MAX_SPP."""
    _check_positive("spp_budget", value, MAX_SPP, "samples per pixel")


def check_budget_buys_a_pass(spp_budget: float | None, step: int) -> None:
    """A sample budget below one pass (`step` spp for every block) renders nothing: refused."""
    if spp_budget is not None and spp_budget < step:
        raise ValueError(f"spp_budget {spp_budget:g} cannot buy one pass of {step} samples per pixel (the step): "
                         f"give a budget of at least {step}, or a smaller step")


def check_reference_image(img: np.ndarray) -> None:
    """A reference with no finite value (all NaN/Inf) would make every figure NaN: refused."""
    finite = np.isfinite(img)
    if not finite.all():
        bad = int(finite.size - np.count_nonzero(finite))
        raise ValueError(f"the reference image has {bad} non-finite value(s) (NaN/Inf) of {img.size}: "
                         "a reference must be finite")


def check_render_args(*, step: Any, min_spp: Any, max_spp: Any, quick_spp: Any, time_limit: Any,
                      spp_budget: Any) -> None:
    """Every numeric argument of run_adaptive, each by its own name."""
    for name, value in (("step", step), ("min_spp", min_spp), ("max_spp", max_spp)):
        check_count(name, value)
    check_count("quick_spp", quick_spp, optional=False)
    check_seconds("time_limit", time_limit)
    check_spp_budget(spp_budget)


def _shown(value: Any) -> str:
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool) and abs(int(value)) >= 10**15:
        return f"a {len(str(abs(int(value))))}-digit number"
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."
