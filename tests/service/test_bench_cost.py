"""benchmarks.bench_cost at a tiny size: the table's structure and the
invariants its parts hold whatever the machine's speed (never a timing goal: those live in
BENCHMARKS.md)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def cost() -> dict:
    from benchmarks.bench_cost import bench_cost

    return bench_cost(size=32, max_spp=64, scenes=("studio_preview",), filters=("box", "gaussian"), repeats=1,
                      crop_spp=4, block=16, command="python -m benchmarks.bench_cost --size 32")


def test_the_cost_per_kept_sample_splits_into_parts_that_multiply_back(cost) -> None:
    """Per case: lanes per kept sample >= 1 (exactly 1 for the uniform loop), the wall split
    into render, decisions and the rest, the first row the product of the next three, the
    headline that ratio with selection divided out; the result is JSON."""
    from benchmarks.bench_cost import FRACTIONS, MODES

    assert [(c["scene"], c["filter"]) for c in cost["cases"]] == [("studio_preview", "box"),
                                                                  ("studio_preview", "gaussian")]
    json.dumps(cost)                                   # what --json writes and `bench --json` emits
    for c in cost["cases"]:
        a, u, q = c["adaptive"], c["uniform"], c["ratios"]
        assert a["criterion"] == "flip" and u["criterion"] == "uniform"
        assert u["samples_kept"] == 32 * 32 * 64 >= a["samples_kept"] > 0
        assert a["lanes"] >= a["samples_kept"] and a["lanes"] == a["samples_traced"]
        assert u["lanes"] == u["samples_kept"]          # uniform traces every tile: no band, nothing dropped
        assert a["launches"] >= 1 and u["launches"] >= 1 and len(a["walls_s"]) == len(u["walls_s"]) == 1
        for x in (a, u):
            assert x["render_s"] > 0 and x["decisions_s"] >= 0
            assert math.isclose(x["render_s"] + x["decisions_s"] + x["rest_s"], x["wall_s"], rel_tol=1e-9)
        assert math.isclose(q["wall_per_kept"], q["wall_over_render"] * q["render_per_lane"] * q["lanes_per_kept"],
                            rel_tol=1e-9)
        assert q["lanes_per_kept"] >= 1.0
        sel = c["selection"]
        assert len(sel["relative"]) == 4 and min(sel["relative"]) > 0    # 16-px blocks of a 32x32 frame
        pixels = np.array([w * h for _, _, w, h in sel["windows"]])
        assert math.isclose(float((np.array(sel["relative"]) * pixels).sum() / pixels.sum()), 1.0, rel_tol=1e-9)
        assert math.isclose(sel["uniform"], 1.0, rel_tol=1e-9) and sel["adaptive"] > 0
        assert math.isclose(c["headline"]["raw"], q["wall_per_kept"])
        assert math.isclose(c["headline"]["selection_divided_out"], q["wall_per_kept"] / sel["adaptive"])
        rows = c["sparse"]["rows"]
        assert {(r["mode"], r["fraction"]) for r in rows} == {(m, f) for m in MODES for f in FRACTIONS} - {("grown", 1.0)}
        dense = next(r for r in rows if r["mode"] == "one" and r["fraction"] == 1.0)
        assert dense["vs_dense"] == 1.0 and dense["lanes"] == 32 * 32 * 16
        for r in rows:                                  # every tile once a round: at least the dense lanes
            assert r["lanes"] >= dense["lanes"] * (1 if r["mode"] == "one" else 2)
            assert r["s_per_lane"] > 0 and np.isfinite(r["vs_dense"])
            if c["filter"] == "box" and r["mode"] == "one":
                assert r["lanes"] == dense["lanes"]     # a box filter traces no guard band


def test_the_markdown_is_one_table_per_scene_and_filter(cost) -> None:
    from benchmarks.bench_cost import md_cost

    text = md_cost(cost)
    assert "`python -m benchmarks.bench_cost --size 32`" in text and cost["variant"] in text
    assert text.count("| part | adaptive | uniform | adaptive / uniform |") == 2
    assert text.count("**overhead per kept sample**") == 2 and "box filter" in text and "gaussian filter" in text
    for part in ("wall per kept sample", "lanes per kept sample", "selection", "trace per lane, 5 % of tiles",
                 "decisions", "launches", "lanes per launch"):
        assert part in text, part
