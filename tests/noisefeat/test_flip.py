"""The batched torch LDR-FLIP (noisefeat.flip, flip_maps, flip_kernels) against NVIDIA's
flip-evaluator, the reference: the same maps and block means to float32 rounding on
realistic noisy blocks, on every extreme input, at block sizes from 1 to 512 pixels, square
or not, and at other viewing distances; FLIP's own filter constants; exact zeros where FLIP
gives them."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.support.extremes import CASES, extreme_halves
from learning.inputs.halves import halves_flip, halves_flip_evaluator
from learning.data.frame_flip import display, flip_map
from noisefeat import flip as F
from noisefeat import flip_kernels as K
from noisefeat import flip_maps as M

RNG = np.random.default_rng(16)
#: agreement asked of the block means (relative) and of the maps (absolute, FLIP in [0, 1])
MEAN_RTOL, MAP_ATOL = 1e-4, 1e-4


def content(n: int, h: int, w: int) -> np.ndarray:
    """Linear RGB scenes with what renders have: smooth coloured shading, hard edges,
    fine texture, dark and saturated regions."""
    y, x = np.mgrid[0:h, 0:w] / max(h, w)
    out = []
    for i in range(n):
        c0, c1 = RNG.random(3) * 0.8, RNG.random(3) * 0.8
        img = c0 + (c1 - c0) * (x * np.cos(i) + y * np.sin(i))[..., None] ** 2
        img = np.where(((x * 7 + i) % 1 < 0.3)[..., None], img * 0.1, img)           # edges, dark bands
        img = img * (1 + 0.3 * np.sin(40 * x + 30 * y + i))[..., None]                 # texture
        out.append(img)
    return np.clip(np.stack(out), 0, None).astype(np.float32)


def noisy_halves(n: int, h: int, w: int, noise: float) -> tuple[np.ndarray, np.ndarray]:
    """Two independent estimates of the same image (noise scaling with the signal, plus
    chroma noise and an occasional firefly), as a path tracer's half buffers are."""
    img = content(n, h, w)
    def one() -> np.ndarray:
        x = img * (1 + noise * RNG.standard_normal(img.shape)) + noise * 0.2 * RNG.random(img.shape)
        x[RNG.random(img.shape[:3]) < 2e-3] *= 20
        return np.clip(x, 0, None).astype(np.float32)
    return one(), one()


def reference_maps(a: np.ndarray, b: np.ndarray, ppd: float = 67.0) -> np.ndarray:
    return np.stack([flip_map(display(x), display(y), ppd) for x, y in zip(a, b)])


@pytest.mark.parametrize("shape", [(64, 64), (128, 128), (8, 8), (24, 40), (53, 17)])
@pytest.mark.parametrize("noise", [0.01, 0.05, 0.3])
def test_block_means_and_maps_match_flip_evaluator(shape, noise):
    a, b = noisy_halves(4, *shape, noise)
    ref = halves_flip_evaluator(a, b)
    got = halves_flip(a, b)
    assert (ref > 1e-3).all()                      # something to see, so relative error means something
    np.testing.assert_allclose(got, ref, rtol=MEAN_RTOL, atol=0)
    maps = M.ldr_flip(display(a), display(b)).numpy()
    np.testing.assert_allclose(maps, reference_maps(a, b), rtol=0, atol=MAP_ATOL)


def test_the_observers_pairs_match_too():
    """Reference against level, not two noise estimates: content that differs (a blurred,
    shifted and recoloured test image), sRGB in and out, as the observer calls FLIP."""
    ref = display(content(3, 48, 72))
    test = np.roll(ref, 2, axis=2) * np.array([1.0, 0.9, 1.1], np.float32)
    test = np.clip((test + np.roll(test, 1, axis=1)) / 2, 0, 1).astype(np.float32)
    maps = M.ldr_flip(ref, test).numpy()
    want = np.stack([flip_map(r, t) for r, t in zip(ref, test)])
    assert want.mean() > 0.05
    np.testing.assert_allclose(maps, want, rtol=0, atol=MAP_ATOL)


@pytest.mark.parametrize("ppd", [20.0, 42.5, 120.0])
def test_other_viewing_distances(ppd):
    """The filter radii follow ppd (FLIP's float32 formulas): 4, 6 and 18 px here."""
    a, b = noisy_halves(2, 40, 40, 0.05)
    np.testing.assert_allclose(halves_flip(a, b, ppd=ppd), halves_flip_evaluator(a, b, ppd=ppd),
                               rtol=MEAN_RTOL, atol=0)


def test_a_large_block_and_tiny_ones():
    a, b = noisy_halves(1, 512, 512, 0.05)
    np.testing.assert_allclose(halves_flip(a, b), halves_flip_evaluator(a, b), rtol=MEAN_RTOL, atol=0)
    for shape in [(1, 1), (1, 5), (3, 2), (2, 40)]:    # smaller than the filters: all clamped
        x, y = (display(RNG.random((2, *shape, 3)).astype(np.float32)) for _ in range(2))
        want = np.stack([flip_map(p, q) for p, q in zip(x, y)])
        np.testing.assert_allclose(M.ldr_flip(x, y).numpy(), want, rtol=0, atol=MAP_ATOL)


@pytest.mark.parametrize("case", CASES)
def test_extreme_inputs_agree_with_flip_evaluator(case):
    a, b = extreme_halves(case, *noisy_halves(3, 16, 16, 0.05))
    got, ref = halves_flip(a, b), halves_flip_evaluator(a, b)
    assert got.shape == ref.shape == (len(a),) and np.isfinite(got).all()
    np.testing.assert_allclose(got, ref, rtol=MEAN_RTOL, atol=1e-7)
    if case in ("black", "constant", "huge"):      # equal display images: exactly 0, as from FLIP
        assert (got == 0).all() and (ref == 0).all()


def test_identical_blocks_are_exactly_zero_in_any_batch():
    a, b = noisy_halves(4, 32, 32, 0.05)
    b[1], b[3] = a[1], a[3]
    b[2] = a[2] * 1e30                             # both clip to the same white
    a[2] = a[2] * 1e31
    e = halves_flip(a, b)
    assert e[1] == e[2] == e[3] == 0.0 and e[0] > 0.01
    assert halves_flip(a[1:2], b[1:2])[0] == 0.0


def test_partly_equal_halves_keep_their_exact_zeros():
    """Where both halves agree over a filter's reach the colour difference is exactly 0,
    and so is FLIP; batching must not leave rounding noise there."""
    a, b = noisy_halves(2, 64, 64, 0.05)
    b[:, :, :32] = a[:, :, :32]
    maps = M.ldr_flip(display(a), display(b)).numpy()
    assert (maps[:, :, :10] == 0).all() and (reference_maps(a, b)[:, :, :10] == 0).all()


def test_batching_and_chunking_do_not_change_a_block(monkeypatch):
    a, b = noisy_halves(5, 24, 24, 0.05)
    together = halves_flip(a, b)
    alone = np.array([halves_flip(a[i:i + 1], b[i:i + 1])[0] for i in range(5)])
    monkeypatch.setattr(M, "CHUNK_PIXELS", 24 * 24 * 2)       # two blocks a chunk
    chunked = halves_flip(a, b)
    np.testing.assert_allclose(alone, together, rtol=1e-6, atol=0)
    np.testing.assert_allclose(chunked, together, rtol=1e-6, atol=0)


def test_filters_are_flips():
    """Radii and normalisation of FLIP.h at 67 ppd: colour filters of radius 10 (Y, Cx sum
    to 1; the two separated Cz Gaussians make a 2D filter of sum 1), feature filters of
    radius ceil(3 x 0.5 x 0.082 x 67) = 9 (Gaussian sum 1, derivative lobes +1 and -1)."""
    c, f = K.colour_kernels(67.0), K.feature_kernels(67.0)
    assert c.shape == (4, 21) and f.shape == (3, 19)
    np.testing.assert_allclose(c[:2].sum(axis=1), 1.0, rtol=1e-12)
    assert abs(c[2].sum() ** 2 + c[3].sum() ** 2 - 1.0) < 1e-12
    assert abs(f[0].sum() - 1) < 1e-12
    for k in f[1:]:
        assert abs(k[k > 0].sum() - 1) < 1e-12 and abs(k[k < 0].sum() + 1) < 1e-12
    assert np.allclose(f[1], -f[1][::-1]) and np.allclose(f[2], f[2][::-1])
    assert len(K.filter_bank(67.0)["Y"]) < 21          # far taps below float32 precision, trimmed
    assert K.spatial_radius(20.0) == 3 and K.spatial_radius(120.0) == 17


def test_empty_batches_and_bad_arguments():
    assert halves_flip(np.zeros((0, 8, 8, 3)), np.zeros((0, 8, 8, 3))).shape == (0,)
    assert M.ldr_flip(np.zeros((0, 8, 8, 3), np.float32), np.zeros((0, 8, 8, 3), np.float32)).shape == (0, 8, 8)
    with pytest.raises(ValueError, match="one shape"):
        F.flip_halves(np.zeros((1, 8, 8, 3)), np.zeros((1, 8, 9, 3)))
    with pytest.raises(ValueError, match="floating point"):
        F.flip_halves(np.zeros((1, 8, 8, 3), np.uint8), np.zeros((1, 8, 8, 3), np.uint8))
    for bad in (0, -1.0, np.nan, np.inf, "far", None):
        with pytest.raises(ValueError, match="ppd"):
            F.flip_halves(np.zeros((1, 8, 8, 3)), np.ones((1, 8, 8, 3)), ppd=bad)
    with pytest.raises(ValueError, match="exposure"):
        halves_flip(np.zeros((1, 8, 8, 3)), np.zeros((1, 8, 8, 3)), exposure=1e9)


def test_exposure_follows_the_display_rule():
    a, b = noisy_halves(2, 32, 32, 0.05)
    np.testing.assert_allclose(halves_flip(a, b, exposure=-2.5), halves_flip_evaluator(a, b, exposure=-2.5),
                               rtol=MEAN_RTOL, atol=0)
    np.testing.assert_allclose(halves_flip(a, b, exposure=1.0), halves_flip(a * 2, b * 2), rtol=1e-6)


def test_torch_inputs_and_float64_work_alike():
    a, b = noisy_halves(2, 16, 16, 0.05)
    e = halves_flip(a, b)
    np.testing.assert_allclose(F.flip_halves(torch.from_numpy(a), torch.from_numpy(b)), e, rtol=1e-7)
    np.testing.assert_allclose(halves_flip(a.astype(np.float64), b.astype(np.float64)), e, rtol=1e-7)
