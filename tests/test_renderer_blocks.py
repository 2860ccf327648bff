"""Crop-window block rendering and the exact block accumulator."""

from __future__ import annotations

import numpy as np
import pytest

from learning.accumulator import BlockAccumulator
from renderer.blocks import BlockRenderer, derive_seed
from renderer.scenes import load_scene


@pytest.fixture(scope="module")
def cornell32() -> BlockRenderer:
    return BlockRenderer(load_scene("cornell", 32), grid=(4, 4))


def test_derive_seed_is_deterministic_and_distinct() -> None:
    seeds = {derive_seed(7, b, p) for b in range(-1, 16) for p in range(20)}
    assert len(seeds) == 17 * 20
    assert all(0 <= s < 2**32 for s in seeds)
    assert derive_seed(7, 3, 2) == derive_seed(7, 3, 2)
    assert derive_seed(7, 3, 2) != derive_seed(8, 3, 2)


def test_grid_must_divide_resolution() -> None:
    scene = load_scene("sky", 30)
    with pytest.raises(ValueError, match="30x30.*4x4"):
        BlockRenderer(scene, grid=(4, 4))
    r = BlockRenderer(scene, grid=(3, 5))
    assert r.block_shape == (10, 6) and r.n_blocks == 15


def test_geometry_is_row_major(cornell32: BlockRenderer) -> None:
    assert cornell32.block_shape == (8, 8)
    assert cornell32.block_origin(0) == (0, 0)
    assert cornell32.block_origin(1) == (8, 0)
    assert cornell32.block_origin(4) == (0, 8)
    assert cornell32.block_slices(15) == (slice(24, 32), slice(24, 32))


@pytest.mark.slow
def test_crop_shape_reproducibility_and_bad_ids(cornell32: BlockRenderer) -> None:
    a = cornell32.render_blocks([0, 7], spp=4, seed=3)
    assert a.shape == (2, 8, 8, 3) and a.dtype == np.float32
    assert np.isfinite(a).all() and (a >= 0).all()
    np.testing.assert_array_equal(a, cornell32.render_blocks([0, 7], spp=4, seed=3))
    b = cornell32.render_blocks([0, 7], spp=4, seed=3, pass_index=1)
    assert not np.array_equal(a, b)
    # the scene is left with its full film afterwards
    assert cornell32.render_full(spp=1, seed=0).shape == (32, 32, 3)
    for bad in ([16], [-1], [1, 1]):
        with pytest.raises(ValueError):
            cornell32.render_blocks(bad, spp=1, seed=0)
    with pytest.raises(ValueError, match="spp"):
        cornell32.render_blocks([0], spp=0, seed=0)


@pytest.mark.slow
def test_quick_image_is_albedo_of_full_frame(cornell32: BlockRenderer) -> None:
    q = cornell32.quick_image()
    assert q.shape == (32, 32, 3)
    assert np.isfinite(q).all()
    assert 0.0 <= q.min() and q.max() <= 1.0  # an albedo, not radiance (the light is ~18)
    assert q.mean() > 0.2


@pytest.mark.slow
def test_direct_quick_image_is_shaded_radiance(cornell32: BlockRenderer) -> None:
    albedo, direct = cornell32.quick_image(), cornell32.quick_image(kind="direct")
    assert direct.shape == (32, 32, 3) and np.isfinite(direct).all() and direct.min() >= 0
    assert direct.max() > 1.0          # radiance: the light itself is far above 1
    assert not np.allclose(direct, albedo, atol=0.05)
    with pytest.raises(ValueError, match="kind"):
        cornell32.quick_image(kind="normals")


def _noise_var(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-pixel variance of mean((a+b)/2) estimated from two equal independent halves."""
    return (a.astype(np.float64) - b) ** 2 / 4.0


@pytest.mark.slow
def test_crop_matches_full_frame_up_to_noise() -> None:
    r = BlockRenderer(load_scene("checker", 32), grid=(4, 4))
    ids = [5, 6, 9, 10, 3]
    spp = 256
    ca = r.render_blocks(ids, spp, seed=11, pass_index=0)
    cb = r.render_blocks(ids, spp, seed=11, pass_index=1)
    fa = r.render_full(spp, seed=11, pass_index=0)
    fb = r.render_full(spp, seed=11, pass_index=1)
    crop = (ca.astype(np.float64) + cb) / 2
    full = (fa.astype(np.float64) + fb) / 2
    ratios, shifted = [], []
    for i, b in enumerate(ids):
        ys, xs = r.block_slices(b)
        expected = _noise_var(ca[i], cb[i]).mean() + _noise_var(fa[ys, xs], fb[ys, xs]).mean()
        ratios.append(((crop[i] - full[ys, xs]) ** 2).mean() / expected)
        xs1 = slice(xs.start - 1, xs.stop - 1)  # negative control: one pixel off
        shifted.append(((crop[i] - full[ys, xs1]) ** 2).mean() / expected)
    # mean squared difference is what noise alone explains (ratio ~ 1) ...
    assert 0.5 < float(np.mean(ratios)) < 2.0, ratios
    # ... and the test can tell a misplaced crop apart
    assert float(np.mean(shifted)) > 3.0, shifted


def test_accumulator_means_are_exact() -> None:
    rng = np.random.default_rng(0)
    acc = BlockAccumulator(grid=(2, 2), block=(3, 4))
    passes = [(rng.random((3, 4, 3)).astype(np.float32), spp) for spp in (5, 7, 5, 1, 9)]
    for img, spp in passes:
        assert acc.add(2, img, spp) == 0
    total = sum(img.astype(np.float64) * spp for img, spp in passes)
    n = sum(spp for _, spp in passes)
    np.testing.assert_allclose(acc.mean(2), total / n, rtol=1e-13)
    assert acc.spp(2) == n and acc.passes(2) == 5 and acc.spp(0) == 0
    np.testing.assert_array_equal(acc.mean(0), 0.0)
    a, b = acc.half_buffer(2)
    even, odd = passes[0::2], passes[1::2]
    np.testing.assert_allclose(a, sum(i.astype(np.float64) * s for i, s in even) / sum(s for _, s in even),
                               rtol=1e-13)
    np.testing.assert_allclose(b, sum(i.astype(np.float64) * s for i, s in odd) / sum(s for _, s in odd),
                               rtol=1e-13)
    assert acc.half_spp(2) == (19, 8)
    full = acc.image()
    assert full.shape == (6, 8, 3)
    np.testing.assert_array_equal(full[3:6, 0:4], acc.mean(2))


def test_accumulator_drops_nonfinite_pixels_only() -> None:
    acc = BlockAccumulator(grid=(1, 1), block=(2, 2))
    acc.add(0, np.full((2, 2, 3), 1.0), 4)
    bad = np.full((2, 2, 3), 3.0)
    bad[0, 0, 1] = np.nan
    bad[1, 1, 2] = np.inf
    assert acc.add(0, bad, 4) == 2
    m = acc.mean(0)
    np.testing.assert_allclose(m[0, 0], 1.0)  # the NaN pass is ignored for that pixel
    np.testing.assert_allclose(m[0, 1], 2.0)  # finite pixels average both passes
    assert acc.nonfinite(0) == 2
    assert acc.spp(0) == 8  # samples spent still count
    assert np.isfinite(acc.image()).all()


def test_accumulator_state_round_trip(tmp_path) -> None:
    rng = np.random.default_rng(1)
    acc = BlockAccumulator(grid=(2, 3), block=(2, 2))
    ids = [0, 4, 5]
    acc.add_many(ids, rng.random((3, 2, 2, 3)), 8)
    acc.add_many(ids[:2], rng.random((2, 2, 2, 3)), 8)
    np.savez(tmp_path / "acc.npz", **acc.state())
    with np.load(tmp_path / "acc.npz") as z:
        back = BlockAccumulator.from_state(dict(z))
    for b in range(6):
        np.testing.assert_array_equal(back.mean(b), acc.mean(b))
        assert back.spp(b) == acc.spp(b) and back.passes(b) == acc.passes(b)
        for x, y in zip(back.half_buffer(b), acc.half_buffer(b)):
            np.testing.assert_array_equal(x, y)
    # resuming continues the even/odd alternation
    img = rng.random((2, 2, 3))
    acc.add(0, img, 8)
    back.add(0, img, 8)
    np.testing.assert_array_equal(back.half_buffer(0)[0], acc.half_buffer(0)[0])
    state = acc.state()
    state["weight"] = state["weight"][:, :3]
    with pytest.raises(ValueError, match="weight"):
        BlockAccumulator.from_state(state)
    with pytest.raises(ValueError, match="lacks"):
        BlockAccumulator.from_state({"grid": np.array([1, 1])})


def test_accumulator_rejects_bad_input() -> None:
    acc = BlockAccumulator(grid=(2, 2), block=(4, 4))
    with pytest.raises(ValueError, match="shape"):
        acc.add(0, np.zeros((4, 5, 3)), 1)
    with pytest.raises(ValueError, match="out of range"):
        acc.add(4, np.zeros((4, 4, 3)), 1)
    with pytest.raises(ValueError, match="spp"):
        acc.add(0, np.zeros((4, 4, 3)), 0)
