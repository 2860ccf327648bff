"""Pooling an error map per block (noisefeat.pooling): layout of the tiles, extremes."""
from __future__ import annotations

import numpy as np
import pytest

from noisefeat.pooling import FLIP_POOLINGS, check_pooling, pool_blocks, pool_maps, tile_starts


def brute_force(m: np.ndarray) -> float:
    ys, xs = tile_starts(m.shape[0]), tile_starts(m.shape[1])
    th, tw = min(16, m.shape[0]), min(16, m.shape[1])
    return max(float(m[y:y + th, x:x + tw].mean()) for y in ys for x in xs)


def test_tiles_are_aligned_to_the_top_left_and_the_last_one_is_flush_with_the_edge():
    assert tile_starts(64).tolist() == [0, 16, 32, 48]
    assert tile_starts(40).tolist() == [0, 16, 24]          # 24..40 overlaps its neighbour
    assert tile_starts(17).tolist() == [0, 1]
    assert tile_starts(16).tolist() == [0] and tile_starts(5).tolist() == [0]   # one tile of the side


@pytest.mark.parametrize("shape", [(64, 64), (40, 37), (16, 16), (5, 70), (1, 1), (128, 48)])
def test_tile_max_equals_the_brute_force_largest_tile_mean(shape):
    m = np.random.default_rng(sum(shape)).random((3, *shape))
    np.testing.assert_allclose(pool_maps(m), [brute_force(x) for x in m], rtol=1e-12)
    np.testing.assert_allclose(pool_maps(m, "mean"), m.mean(axis=(1, 2)), rtol=1e-12)


def test_one_bright_pixel_counts_256_times_more_in_its_tile_than_in_a_64px_block_mean():
    m = np.zeros((1, 64, 64))
    m[0, 37, 5] = 1.0                                        # a firefly's FLIP value, black elsewhere
    assert pool_maps(m)[0] == pytest.approx(1 / 256)
    assert pool_maps(m, "mean")[0] == pytest.approx(1 / 4096)


@pytest.mark.parametrize("value", [0.0, 1e-30, 0.5, 1.0, 1e30, np.finfo(np.float32).max])
def test_constant_maps_pool_to_their_value_at_any_magnitude(value):
    m = np.full((2, 48, 40), value, np.float32)
    for p in FLIP_POOLINGS:
        np.testing.assert_allclose(pool_maps(m, p), float(np.float32(value)), rtol=1e-6)
        assert np.isfinite(pool_maps(m, p)).all()


def test_nan_and_inf_are_not_hidden():
    m = np.zeros((3, 40, 40))
    m[0, 2, 2] = np.nan
    m[1, 39, 39] = np.inf
    for p in FLIP_POOLINGS:
        out = pool_maps(m, p)
        assert np.isnan(out[0]) and out[1] == np.inf and out[2] == 0.0   # only its own map


def test_blocks_are_cut_row_major_and_bad_input_is_one_clear_error():
    m = np.kron(np.arange(6.0).reshape(2, 3), np.ones((20, 30)))
    np.testing.assert_array_equal(pool_blocks(m, (2, 3)), np.arange(6))
    assert pool_maps(np.zeros((0, 8, 8))).shape == (0,)
    with pytest.raises(ValueError, match="unknown pooling 'max'"):
        pool_maps(m[None], "max")
    with pytest.raises(ValueError, match=r"\[N, H, W\]"):
        pool_maps(m)
    with pytest.raises(ValueError, match="grid"):
        pool_blocks(m, (3, 3))
    with pytest.raises(ValueError, match="pixels"):
        pool_maps(np.zeros((1, 0, 4)))
    assert check_pooling("mean") == "mean"
