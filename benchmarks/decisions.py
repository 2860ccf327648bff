"""What the decision sections share: the held-out protocol's checks and their figures' rows.

The sections that judge stopping decisions (`bench_criteria`, `bench_tradeoff`,
`bench_step`) all follow the generalisation protocol (`learning.evaluation.generalisation`):
every knob is calibrated on the training scenes (`--data`), every figure is measured on the
held-out scenes (`--heldout`, scenes no model or threshold was fitted on), per scene, with
the scenes that converge inside their stacks pooled apart from those that never do. Every
stop goes through the one stop rule (`learning.stoprule`).
"""
from __future__ import annotations

from typing import Any

VARIANCE_THRESHOLDS = (0.002, 0.005, 0.01, 0.02, 0.05, 0.07, 0.1, 0.15, 0.2)
KEYS = ("precision", "early_stop_rate", "spp_ratio_vs_oracle", "saved_vs_uniform")


def summary(r: dict[str, Any]) -> dict[str, Any]:
    """Metrics, per scene and per group, and the decision cost per block asked."""
    c = r.get("counters") or {}
    asked = max(1.0, float(c.get("blocks_asked", 0)))
    return {**{k: r[k] for k in KEYS},
            "per_scene": {s: {k: m[k] for k in KEYS} for s, m in r["per_scene"].items()},
            "groups": {g: {k: m[k] for k in (*KEYS, "scenes")} for g, m in (r.get("groups") or {}).items()},
            "decision_ms_per_block": 1e3 * (c.get("features_s", 0.0) + c.get("decisions_s", 0.0)) / asked,
            "blocks_asked": int(c.get("blocks_asked", 0))}


def model_and_check(model: str | None, test_scenes: list[str]) -> Any:
    """The bundle `model` (None: the bundled one), refused if it was trained on a held-out scene."""
    from learning.models.bundle import load_model
    from learning.evaluation.generalisation import check_disjoint

    m = load_model(model)
    check_disjoint(m.manifest.get("training", {}).get("train_scenes") or [], test_scenes)
    return m


def group_line(groups: dict[str, list[str]]) -> str:
    """The sentence naming the held-out scenes that converge and those that mostly never do."""
    from learning.evaluation.generalisation import CONVERGING_SHARE
    return (f"Held-out scenes that converge inside their stacks (at least {CONVERGING_SHARE:.0%} of the blocks "
            f"reach the observer's threshold by the last level): {', '.join(groups.get('converging') or ['none'])}; "
            f"that mostly never converge (they only test 'never stop early'): "
            f"{', '.join(groups.get('not_converging') or ['none'])}.")


def pair(m: dict | None) -> str:
    """A row's early stops / samples vs oracle, as a table cell ("-" for none)."""
    return "-" if not m else f"{m['early_stop_rate']:.3f} / {m['spp_ratio_vs_oracle']:.3f}"
