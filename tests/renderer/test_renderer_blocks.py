"""Block rendering (wavefront and crop engines, windows of any frame) and the exact block accumulator."""

from __future__ import annotations

import numpy as np
import torch
import pytest

from learning.data.accumulator import UnitAccumulator
from renderer.live.blocks import BlockRenderer, derive_seed
from renderer.scenes.catalog import load_scene
from renderer.spec import resolve
from tests.support.windows import block_slices


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
    """Refused at the door, where the spec meets the frame; the renderer takes what it is given."""
    with pytest.raises(ValueError, match="30x30.*4x4"):
        resolve({"grid": (4, 4)}, frame=(30, 30))
    assert resolve({"grid": (3, 3)}, frame=(30, 30)).grid == (3, 3)
    r = BlockRenderer(load_scene("sky", 30), grid=(3, 5))
    assert r.block_shape == (10, 6) and r.n_blocks == 15


def test_geometry_is_row_major(cornell32: BlockRenderer) -> None:
    assert cornell32.block_shape == (8, 8)
    assert cornell32.block_origin(0) == (0, 0)
    assert cornell32.block_origin(1) == (8, 0)
    assert cornell32.block_origin(4) == (0, 8)
    assert block_slices(cornell32, 15) == (slice(24, 32), slice(24, 32))


@pytest.mark.slow
def test_crop_shape_reproducibility_and_bad_ids(cornell32: BlockRenderer) -> None:
    a = cornell32.render_units([0, 7], spp=4, seed=3)
    assert isinstance(a, torch.Tensor) and a.device == cornell32.device    # a pass stays where it was traced
    a = a.numpy()
    assert a.shape == (2, 8, 8, 3) and a.dtype == np.float32
    assert np.isfinite(a).all() and (a >= 0).all()
    np.testing.assert_array_equal(a, cornell32.render_units([0, 7], spp=4, seed=3))
    b = cornell32.render_units([0, 7], spp=4, seed=3, pass_index=1)
    assert not np.array_equal(a, b)
    # the scene is left with its full film afterwards
    assert cornell32.render_full(spp=1, seed=0).shape == (32, 32, 3)
    for bad in ([16], [-1], [1, 1]):
        with pytest.raises(ValueError):
            cornell32.render_units(bad, spp=1, seed=0)
    with pytest.raises(ValueError, match="spp"):
        cornell32.render_units([0], spp=0, seed=0)


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


def _scene(name: str, size: int, rfilter: str = "box", width: int | None = None):
    """A built-in scene with the film's reconstruction filter replaced (published scenes
    mostly use Mitsuba's default, the Gaussian of radius 2 px)."""
    import mitsuba as mi

    from renderer.scenes.catalog import scene_dict

    d = scene_dict(name, size)
    d["sensor"]["film"]["rfilter"] = {"type": rfilter}
    if width is not None:
        d["sensor"]["film"]["width"] = width
    return mi.load_dict(d)


def _mixed_ratio(r: BlockRenderer, a: np.ndarray, b: np.ndarray, fa: np.ndarray, fb: np.ndarray,
                 ids: list[int], shift: int = 0) -> float:
    """Mean squared difference of two renders of the blocks over what their noise explains
    (about 1 for the same estimator; `shift` moves the second one by pixels, a control)."""
    ratios = []
    a, b = np.asarray(a), np.asarray(b)
    for i, blk in enumerate(ids):
        ys, xs = block_slices(r, blk)
        xs = slice(xs.start - shift, xs.stop - shift)
        crop, full = (a[i].astype(np.float64) + b[i]) / 2, (fa[ys, xs].astype(np.float64) + fb[ys, xs]) / 2
        expected = _noise_var(a[i], b[i]).mean() + _noise_var(fa[ys, xs], fb[ys, xs]).mean()
        ratios.append(((crop - full) ** 2).mean() / expected)
    return float(np.mean(ratios))


def test_blocks_are_the_full_frame_bit_for_bit_with_a_box_filter() -> None:
    r = BlockRenderer(_scene("checker", 32), grid=(4, 4))
    assert r.engine == "wavefront" and r.guard == 0
    full = r.render_full(8, seed=11, pass_index=3)
    ids = [5, 6, 9, 3]
    blocks = r.render_units(ids, 8, seed=11, pass_index=3)
    for i, b in enumerate(ids):
        np.testing.assert_array_equal(blocks[i], full[block_slices(r, b)])
    # one block alone, too: its samples do not depend on what else is traced
    np.testing.assert_array_equal(r.render_units([6], 8, seed=11, pass_index=3)[0], blocks[1])
    other = r.render_units(ids, 8, seed=11, pass_index=4)
    assert not np.array_equal(other, blocks)      # a new pass draws new samples


def test_blocks_equal_the_full_frame_with_a_gaussian_filter() -> None:
    """The guard band: a block traced alone gets every sample its filter footprint reaches."""
    r = BlockRenderer(_scene("checker", 32, "gaussian"), grid=(4, 4))
    assert r.guard == 2
    full = r.render_full(8, seed=2)
    ids = [5, 10, 15]
    blocks = r.render_units(ids, 8, seed=2)
    for i, b in enumerate(ids):
        np.testing.assert_allclose(blocks[i], full[block_slices(r, b)], rtol=1e-5, atol=1e-6)
    # control: without the guard band the block's edge pixels miss their neighbours' samples
    r._tracer.guard = 0
    bare = r.render_units([5], 8, seed=2)[0]
    inner = (slice(2, -2), slice(2, -2))
    assert np.abs(bare - full[block_slices(r, 5)]).max() > 1e-3
    np.testing.assert_allclose(bare[inner], full[block_slices(r, 5)][inner], rtol=1e-5, atol=1e-6)


@pytest.mark.slow
def test_wavefront_is_mitsubas_estimator() -> None:
    """The wavefront tracer against mi.render of the same film: differences are noise."""
    import mitsuba as mi

    for rfilter in ("box", "gaussian"):
        scene = _scene("checker", 32, rfilter)
        r = BlockRenderer(scene, grid=(4, 4))
        ids = list(range(16))
        a = r.render_units(ids, 256, seed=1, pass_index=0)
        b = r.render_units(ids, 256, seed=1, pass_index=1)
        fa, fb = (np.asarray(mi.render(scene, spp=256, seed=s), np.float32)[..., :3] for s in (7, 8))
        assert 0.5 < _mixed_ratio(r, a, b, fa, fb, ids) < 2.0, rfilter
        assert _mixed_ratio(r, a, b, fa, fb, [5, 6, 9, 10], shift=1) > 3.0   # the test can fail


@pytest.mark.slow
def test_crop_engine_with_guard_band_matches_full_frame_up_to_noise() -> None:
    """Scalar variants render crop windows: same estimator in distribution, guard band included."""
    r = BlockRenderer(_scene("checker", 32, "gaussian"), grid=(4, 4), engine="crop")
    assert r.engine == "crop" and r.guard == 2
    ids = [5, 6, 9, 10, 3]
    a, b = (r.render_units(ids, 256, seed=11, pass_index=p) for p in (0, 1))
    fa, fb = (r.render_full(256, seed=11, pass_index=p) for p in (0, 1))
    assert 0.5 < _mixed_ratio(r, a, b, fa, fb, ids) < 2.0
    assert _mixed_ratio(r, a, b, fa, fb, [5, 6, 9, 10], shift=1) > 3.0
    assert r.ledger.get("mitsuba_calls") == 2 * len(ids) + 2


COMPILES = """
import json, sys
sys.path.insert(0, {tests!r})
from test_renderer_blocks import _scene
from renderer.live.blocks import BlockRenderer
out = {{}}
for rfilter in ("box", "gaussian"):
    r = BlockRenderer(_scene("cornell", 32, rfilter), grid=(4, 4))
    counts = []
    for p, ids in enumerate((list(range(16)), [0, 1, 2], [7], [3, 12, 15], list(range(0, 16, 2)))):
        r.render_units(ids, 4 + p, seed=0, pass_index=p)   # other blocks, other spp, other pass
        counts.append(r.kernel_compiles)
    r.render_passes([(0, 5), (0, 6), (3, 7)], 4, seed=0)    # several passes in one wavefront
    counts.append(r.kernel_compiles)
    r.render_passes([(1, 8), (2, 9), (4, 10), (5, 11)], 4, seed=0)   # another set, more passes
    counts.append(r.kernel_compiles)
    r.render_passes([(6, 12), (6, 13), (7, 14), (8, 15), (9, 16), (9, 17), (10, 18)], 3, seed=0)   # 7 passes
    counts.append(r.kernel_compiles)
    out[rfilter] = [counts, r.ledger.get("mitsuba_calls"), r.ledger.get("kernel_launches")]
print(json.dumps(out))
"""


def test_one_kernel_compile_per_render_whatever_the_active_set(tmp_path) -> None:
    """In a process with a cold Dr.Jit cache (its own HOME and cache folder): the first pass compiles the
    kernel, no later pass compiles anything, whatever blocks and spp it traces."""
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    tests = str(Path(__file__).parent)
    root = str(Path(__file__).resolve().parents[2])
    env = {**os.environ, "HOME": str(tmp_path), "DRJIT_CACHE_DIR": str(tmp_path / "drjit-cache"),
           "PYTHONPATH": os.pathsep.join([root, tests])}     # cold whatever the caller's cache dir
    done = subprocess.run([sys.executable, "-c", COMPILES.format(tests=tests)], capture_output=True, text=True,
                          env=env, timeout=300)
    assert done.returncode == 0, done.stderr
    for rfilter, (counts, calls, launches) in json.loads(done.stdout.splitlines()[-1]).items():
        # a wide filter's launch of several passes evaluates its samples once and splats each
        # pass from its own lanes: the first such launch compiles those two kernels, later
        # ones nothing, whatever their count of passes
        assert counts == ([1] * 8 if rfilter == "box" else [1] * 5 + [3, 3, 3]), (rfilter, str(counts))
        assert (calls, launches) == (8, 8)       # several passes, one launch, whatever the filter


def test_block_windows_cover_any_frame_with_full_size_edge_windows() -> None:
    r = BlockRenderer(_scene("sky", 70, width=100), block=32)
    assert (r.width, r.height) == (100, 70) and r.grid == (3, 4) and r.overlapping
    assert [r.block_origin(c)[0] for c in range(4)] == [0, 32, 64, 68]
    assert [r.block_origin(4 * k)[1] for k in range(3)] == [0, 32, 38]
    assert r.window(11) == (68, 38, 32, 32)
    assert not BlockRenderer(_scene("sky", 64), block=32).overlapping
    # what the blocks may be is the door's to refuse, where the spec meets the frame
    with pytest.raises(ValueError, match="larger than the 100x70 frame"):
        resolve({"block": 71}, frame=(100, 70))
    with pytest.raises(ValueError, match="either"):
        resolve({"grid": (2, 2), "block": 32})


def test_compose_takes_each_pixel_from_the_window_with_most_samples() -> None:
    from renderer.live.block_windows import compose

    windows = [(0, 0, 4, 4), (2, 0, 4, 4)]                  # 6x4 frame, columns 2-3 shared
    means = [np.full((4, 4, 3), 1.0), np.full((4, 4, 3), 2.0)]
    image, spp, owner = compose(means, windows, [64, 16], (4, 6))
    assert (image[:, :4] == 1.0).all() and (image[:, 4:] == 2.0).all()
    assert (spp[:, :4] == 64).all() and (spp[:, 4:] == 16).all() and (owner[:, 2:4] == 0).all()
    image, spp, owner = compose(means, windows, [16, 64], (4, 6))
    assert (image[:, 2:] == 2.0).all() and (image[:, :2] == 1.0).all()
    with pytest.raises(ValueError, match="cover"):
        compose(means, windows, [1, 1], (4, 7))


def test_accumulator_means_are_exact() -> None:
    rng = np.random.default_rng(0)
    acc = UnitAccumulator(grid=(2, 2), unit_shape=(3, 4))
    passes = [(rng.random((3, 4, 3)).astype(np.float32), spp) for spp in (5, 7, 5, 1, 9)]
    for img, spp in passes:
        assert acc.add(2, img, spp) == 0
    total = sum(img.astype(np.float64) * spp for img, spp in passes)
    n = sum(spp for _, spp in passes)
    np.testing.assert_allclose(acc.mean(2), total / n, rtol=1e-13)
    assert acc.spp(2) == n and acc.pass_count(2) == 5 and acc.spp(0) == 0
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
    acc = UnitAccumulator(grid=(1, 1), unit_shape=(2, 2))
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
    acc = UnitAccumulator(grid=(2, 3), unit_shape=(2, 2))
    ids = [0, 4, 5]
    acc.add_many(ids, rng.random((3, 2, 2, 3)), 8)
    acc.add_many(ids[:2], rng.random((2, 2, 2, 3)), 8)
    np.savez(tmp_path / "acc.npz", **acc.state())
    with np.load(tmp_path / "acc.npz") as z:
        back = UnitAccumulator.from_state(dict(z))
    for b in range(6):
        np.testing.assert_array_equal(back.mean(b), acc.mean(b))
        assert back.spp(b) == acc.spp(b) and back.pass_count(b) == acc.pass_count(b)
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
        UnitAccumulator.from_state(state)
    with pytest.raises(ValueError, match="lacks"):
        UnitAccumulator.from_state({"grid": np.array([1, 1])})


def test_accumulator_rejects_bad_input() -> None:
    acc = UnitAccumulator(grid=(2, 2), unit_shape=(4, 4))
    with pytest.raises(ValueError, match="shape"):
        acc.add(0, np.zeros((4, 5, 3)), 1)
    with pytest.raises(ValueError, match="out of range"):
        acc.add(4, np.zeros((4, 4, 3)), 1)
    with pytest.raises(ValueError, match="spp"):
        acc.add(0, np.zeros((4, 4, 3)), 0)
