"""The stability matrix: no entry point crashes or returns NaN/Inf on extreme input."""
from __future__ import annotations

import pytest

from benchmarks.stability import extreme_inputs, matrix, other_cells


@pytest.fixture(scope="module")
def cells():
    return matrix()


def test_every_cell_is_finite_or_a_clear_rejection(cells):
    for entry, row in cells.items():
        for kind, result in row.items():
            assert result == "finite" or result.startswith("rejected: "), (entry, kind, result)


def test_expected_rejections_and_acceptances(cells):
    for entry, row in cells.items():
        assert row["black"] == row["NaN / +-Inf pixels"] == row["fireflies 1e6"] == "finite", entry
        assert row["empty batch"] == "finite", entry
    for entry in ("extract_features", "service infer", "render loop: model criterion"):
        assert "at least 8x8" in cells[entry]["7x7 blocks (too small)"]
    assert all(v == "finite" for v in cells["render loop: flip criterion"].values())   # FLIP takes any size
    assert "FP32" in cells["service infer"]["float16"]        # the protocol's datatype rule
    raw = cells["model decision (svm, raw L* of 16x16 blocks)"]
    for size in ("8x8 blocks", "1024x1024 block", "7x7 blocks (too small)"):
        assert "takes 16x16 blocks (its training size), got" in raw[size], raw[size]
    transfer = next(v for k, v in cells.items() if "mobilenet_v2" in k)
    assert all(v == "finite" for v in transfer.values()), transfer   # it resizes every block
    assert set(extreme_inputs()) == set(next(iter(cells.values())))


def test_stacks_spp_and_hyperparameter_extremes(tmp_path):
    other = other_cells(tmp_path)
    assert len(other) >= 9
    for name, result in other.items():
        assert result == "finite", (name, result)
