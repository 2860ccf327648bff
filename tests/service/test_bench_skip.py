"""benchmarks.bench_skip on a small synthetic stack: every knob pair is measured at each grain
against every pass judged; the knobs ask fewer units here, and at block grain, where a
verdict reads its level alone, a unit judged less often never stops sooner (what the knobs
cost on held-out scenes is in BENCHMARKS.md)."""
from __future__ import annotations

import json

import numpy as np
import pytest

pytestmark = pytest.mark.slow


def test_each_knob_pair_is_measured_against_every_pass_judged(tmp_path) -> None:
    from benchmarks.bench_skip import bench_skip, knob_key, md_skip
    from learning.data.synthetic import make_synthetic_stack

    make_synthetic_stack(tmp_path / "synthetic", size=64, spp=list(range(16, 257, 16)), seed=5)
    knobs = ((0.0, 0.0), (0.5, 0.0), (0.5, 0.25))
    r = bench_skip(None, heldout=str(tmp_path), taus=(0.02,), knobs=knobs)
    json.dumps(r)
    for grain in ("tile", "block"):
        every, skip, floor = (r["runs"][knob_key(0.02, grain, s, g)] for s, g in knobs)
        assert every["asked"] >= skip["asked"] >= floor["asked"] > 0
        spp = [sum(p["spp"] for p in run["per_scene"].values()) for run in (every, skip, floor)]
        assert np.all(np.isfinite(spp)) and min(spp) > 0
        if grain == "block":                            # later decisions: never earlier stops
            assert spp[0] <= spp[1] <= spp[2]
    text = md_skip(r)
    assert "| 0 | 0 |" in text and "| 0.5 | 0.25 |" in text and "1.00x" in text
    with pytest.raises(ValueError, match="--heldout"):
        bench_skip(None)
