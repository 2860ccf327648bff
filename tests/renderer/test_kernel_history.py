"""A render's memory does not grow with its passes: Dr.Jit's kernel history, which keeps a
record of every kernel run until it is read, is read (and emptied) after every launch."""
from __future__ import annotations

import pytest

from renderer.live.blocks import BlockRenderer
from tests.renderer.test_renderer_blocks import _scene


def test_every_launch_leaves_the_kernel_history_empty() -> None:
    dr = pytest.importorskip("drjit")
    with BlockRenderer(_scene("cornell", 16), grid=(1, 1)) as r:
        if not r._counts_kernels:
            pytest.skip("a scalar variant keeps no kernel history")
        for p in range(6):               # passes of a long render, one launch each
            r.render_passes([(0, p)], 1, seed=1)
            left = dr.kernel_history()
            assert left == [], f"{len(left)} kernel records left after launch {p}"
        assert r.ledger.get("kernel_launches") >= 6
