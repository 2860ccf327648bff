"""The stability matrix: every public numeric entry point against extreme inputs.

Each cell is what the entry point did: "finite" (returned finite, documented results) or
"rejected: <message>" (a clear ValueError / 4xx). Anything else (an unexpected exception,
a NaN or Inf in the output) is a defect, which tests/service/test_stability.py asserts never
happens; `noisestop bench stability` writes the matrix into BENCHMARKS.md.
"""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

Entry = Callable[[np.ndarray], Any]


def extreme_inputs(seed: int = 0) -> dict[str, np.ndarray]:
    """Block batches [N, h, w, 3] of linear RGB at the extremes: black, constant, fireflies,
    NaN and Inf pixels, huge and tiny values, half floats, odd block sizes, an empty batch."""
    rng = np.random.default_rng(seed)
    base = (rng.random((4, 16, 16, 3)) * 0.3).astype(np.float32)
    fire = base.copy()
    fire[:, ::5, ::7] = 1e6
    bad = base.copy()
    bad[0, 1, 1, 0], bad[1, 2, 2, :], bad[2, 3, 3, 1] = np.nan, np.inf, -np.inf
    return {
        "black": np.zeros((4, 16, 16, 3), np.float32),
        "constant": np.full((4, 16, 16, 3), 0.5, np.float32),
        "fireflies 1e6": fire,
        "NaN / +-Inf pixels": bad,
        "huge 1e30": base * np.float32(1e30),
        "tiny 1e-30": base * np.float32(1e-30),
        "float16": base.astype(np.float16),
        "8x8 blocks": base[:, :8, :8],
        "1024x1024 block": (rng.random((1, 1024, 1024, 3)) * 0.3).astype(np.float32),
        "7x7 blocks (too small)": base[:, :7, :7],
        "empty batch": np.zeros((0, 16, 16, 3), np.float32),
    }


def entry_points(model=None) -> dict[str, Entry]:
    """name -> callable(blocks) for features, the model, the service and the render loop."""
    from learning.models.bundle import load_model
    from noisefeat import extract_features
    from renderer.criteria import UnitView, FlipCriterion, ModelCriterion, VarianceCriterion
    from service.oip import ApiError
    from learning.inputs.noise_input import halves_input
    from service.registry import ServedModel

    m = model or load_model()
    served = ServedModel("stability", m, 0.0)

    def service(blocks: np.ndarray) -> Any:  # sent as is: the protocol's FP32 rule decides
        try:
            out, _ = served.infer(served.image_inputs(blocks))
        except ApiError as exc:
            raise ValueError(f"HTTP {exc.status}: {exc}") from None
        return out["score"]

    def views(blocks: np.ndarray, halves: bool) -> list:
        b = np.asarray(blocks)
        return [UnitView(mean=x, spp=16, halves=(x, x * 0.9) if halves else None,
                          half_spp=(8, 8) if halves else None, quick=x) for x in b]

    def render_model(blocks: np.ndarray) -> Any:
        return ModelCriterion(m).decide(list(range(len(blocks))), views(blocks, m.needs_halves)).verdict

    def model_decision(blocks: np.ndarray) -> Any:
        b = np.asarray(blocks)
        return (m.score_halves(b, b * 0.9) if m.needs_halves else m.score_blocks(b, b))[1]

    def render_flip(blocks: np.ndarray) -> Any:
        return FlipCriterion(0.02).decide(list(range(len(blocks))), views(blocks, True)).verdict

    def render_variance(blocks: np.ndarray) -> Any:
        return VarianceCriterion().decide(list(range(len(blocks))), views(blocks, True)).verdict

    raw_svm, transfer = small_models()
    return {
        "extract_features": extract_features,
        f"model decision ({m.name})": model_decision,
        "halves input": lambda b: halves_input(b, np.asarray(b) * 0.9),
        "model decision (svm, raw L* of 16x16 blocks)": lambda b: raw_svm.score_blocks(b)[1],
        f"model decision ({transfer.report_label()})": transfer.decision_function,
        "service infer": service,
        "render loop: model criterion": render_model,
        "render loop: variance criterion": render_variance,
        "render loop: flip criterion": render_flip,
    }


def small_models(seed: int = 0):
    """A raw-pixel SVM bundle-model and a transfer baseline (MobileNetV2, untrained base,
    two epochs), both fit on seeded random 16x16 blocks: the other decision routes a user
    can train, driven through the same extremes as the bundled model."""
    from learning.models.bundle import Model
    from learning.models.estimators import SVM
    from learning.inputs.table import raw_input
    from learning.models.transfer import TransferClassifier

    rng = np.random.default_rng(seed)
    blocks = (rng.random((48, 16, 16, 3)) * np.linspace(0.05, 1, 48)[:, None, None, None]).astype(np.float32)
    y = np.where(np.arange(48) % 2 == 0, 1, -1)
    raw = Model(SVM(C=10, gamma="scale").fit(raw_input(blocks), y), {"kind": "svm", "input": "raw"})
    transfer = TransferClassifier("mobilenet_v2", epochs=2, batch_size=16).fit(blocks, y)
    return raw, transfer


def cell(entry: Entry, blocks: np.ndarray) -> str:
    """'finite' or 'rejected: ...'; anything else means a defect: 'DEFECT: ...'."""
    try:
        out = entry(blocks)
    except ValueError as exc:
        return f"rejected: {str(exc).splitlines()[0][:90]}"
    except Exception as exc:  # noqa: BLE001 - the matrix records it as a defect
        return f"DEFECT: {type(exc).__name__}: {str(exc)[:80]}"
    arr = np.asarray(out, dtype=np.float64) if not isinstance(out, tuple) else np.concatenate(
        [np.asarray(o, np.float64).ravel() for o in out])
    return "finite" if np.isfinite(arr).all() else "DEFECT: non-finite output"


def matrix(model=None) -> dict[str, dict[str, str]]:
    inputs = extreme_inputs()
    return {name: {kind: cell(fn, blocks) for kind, blocks in inputs.items()}
            for name, fn in entry_points(model).items()}


def other_cells(tmp_dir) -> dict[str, str]:
    """Extremes that are not block batches: stacks, spp values, SVM hyper-parameters."""
    from pathlib import Path

    from learning.models.cv import C_GRID, GAMMA_FACTORS, scale_gamma
    from learning.models.estimators import DSVM
    from learning.evaluation.metrics import evaluate_verdicts
    from learning.data.synthetic import make_synthetic_stack
    from learning.stoprule import StopRule
    from renderer.criteria import FlipCriterion, OracleCriterion, VarianceCriterion
    from renderer.simulation.simulate import simulate_stack

    def run(fn: Callable[[], Any]) -> str:
        return cell(lambda _: fn(), np.zeros(0))

    one = make_synthetic_stack(Path(tmp_dir) / "one", size=32, spp=(16,))
    rng = np.random.default_rng(0)
    X = rng.normal(size=(200, 26))
    y = np.where(X[:, 0] > 0, 1, -1)
    cells = {
        "single-level stack, variance simulation": run(lambda: simulate_stack(one, VarianceCriterion())),
        "single-level stack, oracle simulation": run(lambda: simulate_stack(one, OracleCriterion(one.thresholds))),
        "single-level stack, flip simulation": run(lambda: simulate_stack(one, FlipCriterion(0.02))),
        "stop rule, scores NaN / +-Inf / +-1e300": run(lambda: StopRule(0.0, 16).stops(
            np.array([[np.nan, np.inf, -np.inf, 1e300, -1e300]] * 3), [8, 16, 24])),
    }
    for spp in ([1], [10 ** 6], [1, 10 ** 6]):
        v = np.ones((len(spp), 2), int)
        cells[f"metrics with spp {spp}"] = run(lambda spp=spp, v=v: [
            x for k, x in evaluate_verdicts({"s": (v, v, [spp[-1], None], spp)}).items() if k != "per_scene"])
    g0 = scale_gamma(X, True)
    for C in (C_GRID[0], C_GRID[-1]):
        for f in (GAMMA_FACTORS[0], GAMMA_FACTORS[-1]):
            cells[f"DSVM with C={C:g}, gamma={g0 * f:.3g}"] = run(
                lambda C=C, f=f: DSVM(C=C, gamma=g0 * f).fit(X, y).decision_function(X))
    return cells


def markdown(m: dict[str, dict[str, str]]) -> str:
    names = list(m)
    kinds = list(next(iter(m.values())))
    lines = ["| input | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for k in kinds:
        lines.append(f"| {k} | " + " | ".join(m[n][k] for n in names) + " |")
    return "\n".join(lines)
