"""The adaptive render's checkpoint (out/checkpoint.npz), where the typed progress becomes arrays and
back: written atomically with a digest, read without pickle, trusted only when made with the same
settings and holding a state the loop could have produced (else one ValueError naming the file; what
the file cannot vouch for: `renderer.live.checkpoint_checks`)."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from learning.data.accumulator import UnitAccumulator
from learning.inputs.history import last_decided_spp
from noisefeat.atomic import atomic_write
from learning.data.npz import check_digest, read_npz, savez_bytes

from ..criteria import external_counters, internal_counters
from .progress import BudgetState, LoopState, Progress, RunSettings

CHECKPOINT = "checkpoint.npz"
CHECKPOINT_FORMAT = "noisestop-adaptive-checkpoint"
CHECKPOINT_VERSION = 6          # raised whenever an array is added or its meaning changes

#: where this code's name differs from the checkpoint's array name (the file's names stay;
#: the counters': `renderer.criteria.EXTERNAL_COUNTER_NAMES`)
ARRAY_NAMES = {"rows": "pass_index", "history_unit_spp": "history_block_spp"}


def settings_record(settings: RunSettings) -> dict[str, Any]:
    """`settings` as the checkpoint records them and a resume compares: JSON, with no
    spp_budget key without a sample budget."""
    record = json.loads(json.dumps(dataclasses.asdict(settings)))
    if record["spp_budget"] is None:
        del record["spp_budget"]
    return record


def save_checkpoint(path: Path, progress: Progress, settings: RunSettings) -> None:
    loop, n = progress.loop, len(progress.loop.active)
    counters = external_counters(progress.counters)
    arrays: dict[str, np.ndarray] = {
        "format": np.array(CHECKPOINT_FORMAT),          # 0-d unicode arrays: no pickle needed
        "version": np.int64(CHECKPOINT_VERSION),
        "settings": np.array(json.dumps(settings_record(settings), sort_keys=True)),
        "active": np.asarray(loop.active, bool),
        "stop_spp": np.asarray(loop.stop_spp, np.int64),
        "history": np.asarray(loop.history, np.int8).reshape(-1, n),
        "history_spp": np.asarray(loop.history_spp, np.int64),
        ARRAY_NAMES["history_unit_spp"]: np.asarray(loop.history_unit_spp, np.int64).reshape(-1, n),
        "rendered": np.asarray(loop.rendered, np.int64),
        "evidence": np.asarray(loop.evidence, np.float64).reshape(-1, 2),
        "next_spp": np.asarray(loop.next_spp, np.int64),
        ARRAY_NAMES["rows"]: np.int64(loop.rows),
        "done": np.bool_(progress.done),
        "counter_names": np.array(list(counters), dtype="<U64"),
        "counter_values": np.array(list(counters.values()), np.int64),
        "timer_names": np.array(list(progress.timers), dtype="<U64"),
        "timer_values": np.array(list(progress.timers.values()), np.float64),
        "quick": np.zeros((0, 0, 3), np.float32) if progress.quick is None else progress.quick,
    }
    arrays.update({f"acc_{k}": v for k, v in loop.acc.state().items()})
    b = progress.budget
    if b is not None:          # a budget render: its blocks may be out of step
        arrays.update({"budget_prioritised_rounds": np.int64(b.prioritised_rounds),
                       "budget_ended": np.bool_(b.ended), "budget_cost": np.asarray(b.cost, np.float64),
                       "budget_ratio_asked": np.asarray(b.ratio_asked, bool),
                       "budget_ratio": np.asarray(b.ratio, np.float64)})
    atomic_write(path, savez_bytes(arrays, with_digest=True))


def expected_bytes(frame: tuple[int, int], n_units: int, n_passes: int, unit_shape: tuple[int, int]) -> int:
    """An upper bound on a valid checkpoint's size: both halves' sums and weights over every
    block window (overlapping windows hold more than the frame), the quick image, a history
    row per pass (a budget render: per round), and slack for names."""
    h, w = frame
    held = max(h * w, n_units * unit_shape[0] * unit_shape[1])
    rows = n_passes * n_units          # a budget render's rounds: one block's pass each, at worst
    return 2 * held * (3 * 8 + 8) + h * w * 3 * 4 + rows * (9 * n_units + 24) + 32 * n_units + (1 << 20)


def load_checkpoint(path: Path, settings: RunSettings, *, pass_spp: list[int], grid: tuple[int, int],
                    unit_shape: tuple[int, int], frame: tuple[int, int], nonnegative: bool = True) -> Progress:
    """The progress a checkpoint saved with these settings holds (its accumulator on the
    host), or ValueError. `nonnegative`: the film's filter has no negative lobe (radiance sums
    >= 0)."""
    n = grid[0] * grid[1]
    try:
        data = read_npz(path, max_bytes=expected_bytes(frame, n, len(pass_spp), unit_shape), kind="checkpoint")
        return _validated(path, data, settings_record(settings), pass_spp, grid, unit_shape, frame, nonnegative)
    except ValueError as exc:
        if "start over" in str(exc):
            raise
        raise ValueError(f"{exc}; delete it (or rerun without --resume) to start over") from None


def _get(data: dict[str, np.ndarray], key: str, dtype: str, shape: tuple[int, ...] | None = None) -> np.ndarray:
    arr = data.get(key)
    if arr is None:
        raise ValueError(f"no {key!r}")
    kind_ok = arr.dtype.kind == "U" if dtype == "U" else arr.dtype == np.dtype(dtype)
    if not kind_ok:
        raise ValueError(f"{key!r} is {arr.dtype}, expected {dtype}")
    if shape is not None and arr.shape != shape:
        raise ValueError(f"{key!r} has shape {list(arr.shape)}, expected {list(shape)}")
    return arr


def _validated(path: Path, data: dict[str, np.ndarray], settings: dict[str, Any], pass_spp: list[int],
               grid: tuple[int, int], unit_shape: tuple[int, int], frame: tuple[int, int],
               nonnegative: bool) -> Progress:
    fmt, version = data.get("format"), data.get("version")
    if fmt is None or fmt.shape != () or str(fmt) != CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: not a noisestop adaptive-render checkpoint")
    if version is None or version.shape != () or version.dtype.kind != "i" or int(version) != CHECKPOINT_VERSION:
        raise ValueError(f"{path}: checkpoint version {None if version is None else version.tolist()!r}, this "
                         f"noisestop reads version {CHECKPOINT_VERSION}")
    try:
        check_digest(path, data)
        saved = json.loads(str(_get(data, "settings", "U", ())))
    except (ValueError, RecursionError) as exc:
        raise ValueError(f"{path}: {exc}" if str(path) not in str(exc) else str(exc)) from None
    if saved != settings:
        if not isinstance(saved, dict):
            raise ValueError(f"{path}: settings are not an object")
        diff = [f"{k}: {saved.get(k)!r} then, {settings.get(k)!r} now"
                for k in sorted(set(saved) | set(settings)) if saved.get(k) != settings.get(k)]
        raise ValueError(f"{path}: checkpoint was made with other settings ({'; '.join(diff)}); "
                         "rerun with the same options or without --resume to start over")
    try:
        return _state(data, pass_spp, grid, unit_shape, frame, nonnegative)
    except ValueError as exc:
        raise ValueError(f"{path}: inconsistent checkpoint: {exc}") from None


#: the largest radiance one pass of a pixel can hold (Mitsuba's images are float32)
PASS_MAX = float(np.finfo(np.float32).max)
#: the largest counter a checkpoint may hold: past any render, yet far enough below int64's
#: end that a resumed run's own counts cannot overflow it
MAX_COUNTER = 1 << 53
#: the longest timer, seconds: a century (a forged 1e308 would be reported as wall_s)
MAX_TIMER_S = 100 * 365 * 24 * 3600.0


def _check_meaning(acc: dict[str, np.ndarray], nonnegative: bool) -> None:
    """What the accumulator's arrays mean beyond shapes and types (a digest recomputed over
    forged values passes; these do not): a pixel's weight is its half's finite samples, all of
    them where its block dropped nothing; a sum is at most weight x the largest float32
    radiance, and >= 0 when the film's filter has no negative lobe."""
    total, weight, spp, dropped = acc["sum"], acc["weight"], acc["spp"], acc["nonfinite"]
    half_spp = spp.T[:, :, None, None]                          # [2, n, 1, 1]
    if (weight > half_spp).any():
        raise ValueError("a pixel's weight exceeds its half buffer's samples")
    short = (weight < half_spp).sum(axis=(0, 2, 3))             # pixels that dropped a pass, per block
    if (short > dropped).any():
        raise ValueError("more pixels short of their samples than the values their block dropped")
    if (np.abs(total) > PASS_MAX * weight[..., None]).any():
        raise ValueError("a sum exceeds its weight times the largest float32 radiance")
    if nonnegative and (total < 0).any():
        raise ValueError("negative radiance sums, with a film filter that has no negative lobe "
                         "(a scene with negative emitters or textures cannot resume)")


def _state(data: dict[str, np.ndarray], pass_spp: list[int], grid: tuple[int, int], unit_shape: tuple[int, int],
           frame: tuple[int, int], nonnegative: bool) -> Progress:
    n = grid[0] * grid[1]
    budget = "budget_cost" in data
    p = int(_get(data, ARRAY_NAMES["rows"], "int64", ()))
    if not 0 <= p <= (n * len(pass_spp) if budget else len(pass_spp)):
        raise ValueError(f"pass {p} claimed, these settings make {len(pass_spp)} passes")
    active = _get(data, "active", "bool", (n,))
    stop_spp = _get(data, "stop_spp", "int64", (n,))
    history = _get(data, "history", "int8", (p, n))
    history_spp = _get(data, "history_spp", "int64", (p,))
    unit_spp = _get(data, ARRAY_NAMES["history_unit_spp"], "int64", (p, n))
    rendered = _get(data, "rendered", "int64", (p,))
    evidence = _get(data, "evidence", "float64", (n, 2))
    next_spp = _get(data, "next_spp", "int64", (n,))
    done = bool(_get(data, "done", "bool", ()))
    cum = np.concatenate([[0], np.cumsum(pass_spp, dtype=np.int64)])   # [0, *schedule]
    decided_spp = last_decided_spp(history, unit_spp)
    if not np.isfinite(evidence).all() or (evidence < 0).any() or (evidence[:, 1] != np.round(evidence[:, 1])).any() \
            or (evidence[:, 1] > decided_spp).any() or ((evidence[:, 1] == 0) & (evidence[:, 0] != 0)).any():
        raise ValueError("the decision history's evidence is not finite sums >= 0 weighing at most the samples "
                         "of the unit's decisions")
    if (next_spp < decided_spp).any() or (next_spp > (decided_spp << 20)).any():
        raise ValueError("a unit's next decision is before its last one or past what any ratio asks")
    if not np.isin(history, (-1, 0, 1)).all():
        raise ValueError("history holds values other than -1, 0, +1")
    if ((rendered < 1) | (rendered > n)).any():
        raise ValueError(f"a pass rendered a number of blocks outside 1..{n}")
    if (unit_spp < 0).any() or (unit_spp > cum[-1]).any() or (p > 1 and (np.diff(unit_spp, axis=0) < 0).any()):
        raise ValueError("the per-block spp history is out of range or decreases")
    if not np.array_equal(~active, (history > 0).any(axis=0)):
        raise ValueError("stopped blocks disagree with the verdict history")
    first = np.argmax(history > 0, axis=0)
    stopped_at = np.where(~active, unit_spp[first, np.arange(n)] if p else 0, 0)
    if not np.array_equal(stop_spp, stopped_at):
        raise ValueError("stopped blocks and their stop spp disagree with the verdict history")
    if not budget:
        if not np.array_equal(history_spp, cum[1:p + 1]):
            raise ValueError("history spp are not the schedule (cumulative pass spp)")
        if done != (p == len(pass_spp) or not active.any()):
            raise ValueError(f"done is {done} at pass {p} of {len(pass_spp)} with {int(active.sum())} blocks active")
    names = _get(data, "counter_names", "U")
    values = _get(data, "counter_values", "int64", names.shape)
    tnames = _get(data, "timer_names", "U")
    tvalues = _get(data, "timer_values", "float64", tnames.shape)
    if names.ndim != 1 or tnames.ndim != 1 or (values < 0).any() or (values > MAX_COUNTER).any() \
            or not np.isfinite(tvalues).all() or (tvalues < 0).any() or (tvalues > MAX_TIMER_S).any():
        raise ValueError(f"counters must be whole numbers in [0, 2**53] and timers seconds in [0, {MAX_TIMER_S:.3g}]")
    quick = _get(data, "quick", "float32")
    if quick.shape not in ((0, 0, 3), (frame[0], frame[1], 3)):
        raise ValueError(f"quick image of shape {list(quick.shape)}, the frame is {frame[1]}x{frame[0]}")
    acc_state = {k[4:]: v for k, v in data.items() if k.startswith("acc_")}
    for key, want in (("grid", grid), ("block", unit_shape)):
        got = acc_state.get(key)
        if got is None or got.shape != (2,) or got.dtype.kind != "i" or tuple(int(v) for v in got) != tuple(want):
            raise ValueError(f"accumulator {key} {None if got is None else got.tolist()} is not the render's "
                             f"{list(want)}")
    if int(_get(acc_state, "version", "int64", ())) != UnitAccumulator.STATE_VERSION:
        raise ValueError(f"accumulator state version {acc_state['version']}, this code reads "
                         f"{UnitAccumulator.STATE_VERSION}")
    for key, dtype, shape in (("sum", "float64", (2, n, *unit_shape, 3)), ("weight", "int64", (2, n, *unit_shape)),
                              ("spp", "int64", (n, 2)), ("passes", "int64", (n,)), ("nonfinite", "int64", (n,))):
        arr = _get(acc_state, key, dtype, shape)
        if arr.dtype.kind == "f" and not np.isfinite(arr).all():
            raise ValueError(f"accumulator {key!r} holds NaN or Inf")
        most = {"weight": int(cum[-1]), "passes": len(pass_spp)}.get(key)
        if arr.dtype.kind == "i" and ((arr < 0).any() or (most is not None and (arr > most).any())):
            raise ValueError(f"accumulator {key!r} out of range")
    _check_meaning(acc_state, nonnegative)
    acc = UnitAccumulator.from_state(acc_state)
    spp, pass_counts = acc.spp_all(), acc.pass_counts()
    if not np.array_equal(spp, cum[pass_counts]) or (p and not np.array_equal(unit_spp[-1], spp)) \
            or (not p and spp.any()) or (not budget and not (pass_counts[active] == p).all()):
        raise ValueError("the accumulated samples disagree with the passes and stops")
    progress = Progress(
        LoopState(acc=acc, active=active, stop_spp=stop_spp, history=history, history_spp=history_spp,
                  history_unit_spp=unit_spp, rendered=rendered, evidence=evidence, next_spp=next_spp),
        done=done, counters=internal_counters(dict(zip(names.tolist(), values.tolist()))),
        timers=dict(zip(tnames.tolist(), tvalues.tolist())), quick=None if quick.size == 0 else quick)
    if budget:
        rounds = int(_get(data, "budget_prioritised_rounds", "int64", ()))
        ended = bool(_get(data, "budget_ended", "bool", ()))
        cost = _get(data, "budget_cost", "float64", (2,))
        ratio_asked = _get(data, "budget_ratio_asked", "bool", (n,))
        ratio = _get(data, "budget_ratio", "float64", (n,))
        asked = ratio[ratio_asked]
        if not (0 <= rounds <= p) or not np.isfinite(cost).all() or (cost < 0).any() \
                or (asked < 0).any() or np.isinf(asked).any():
            raise ValueError("budget state out of range (a ratio is NaN or finite and >= 0)")
        if cost[1] != float(spp.sum()):
            raise ValueError(f"the budget counts {cost[1]:g} block-spp rendered, the accumulator holds "
                             f"{int(spp.sum())}")
        left = active & (pass_counts < len(pass_spp))
        if done != (not left.any() or ended):
            raise ValueError(f"done is {done} with {int(left.sum())} blocks able to take a pass")
        progress.budget = BudgetState(prioritised_rounds=rounds, ended=ended, cost=(float(cost[0]), float(cost[1])),
                                      ratio_asked=ratio_asked, ratio=ratio)
    return progress
