"""noisefeat: equivalence with plain convolutions and PyWavelets, and the extremes."""
from __future__ import annotations

import numpy as np
import pytest
import pywt
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from noisefeat import FEATURE_NAMES, FeatureBase, extract_features, merge_blocks, split_blocks
from noisefeat.display import display, lightness, srgb_decode, srgb_encode
from noisefeat.wavelet import lowpass_projection
from noisefeat.weights import load_kernels, save_kernels, smoothing_kernels


@pytest.fixture(scope="module")
def base() -> FeatureBase:
    return FeatureBase().eval()


def spatial_features(fb: FeatureBase, x: torch.Tensor) -> torch.Tensor:
    """The definition, computed the slow way: torch.conv2d and the spatial wavelet."""
    x = x.double()
    outs = [o.double() for o in fb.layer_outputs(x)]
    means = torch.stack([(x - o)[:, 0].mean((-2, -1)) for o in outs], 1)
    stds = torch.stack([(x - o)[:, 0].std((-2, -1), correction=0) for o in outs], 1)
    return torch.cat([means, stds], 1).float()


def perturbed(wavelet: str = "haar", seed: int = 0) -> FeatureBase:
    """A base with non-normalised kernels, as training may leave them."""
    fb = FeatureBase(wavelet=wavelet).eval()
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for conv in fb.convs:
            conv.weight.add_(0.05 * torch.randn(conv.weight.shape, generator=gen))
    return fb


@pytest.mark.parametrize("wavelet", ["haar", "db2", "bior2.2"])
@pytest.mark.parametrize("shape", [(8, 8), (16, 12), (9, 11), (40, 33)])
def test_spectral_route_equals_conv2d(wavelet, shape):
    fb = perturbed(wavelet)
    x = torch.rand(3, 1, *shape, generator=torch.Generator().manual_seed(1)) * 100
    with torch.no_grad():
        fast, slow = fb(x), spatial_features(fb, x)
    np.testing.assert_allclose(fast.numpy(), slow.numpy(), rtol=1e-4, atol=2e-4)


@pytest.mark.parametrize("wavelet", ["haar", "db2", "sym4"])
@pytest.mark.parametrize("shape", [(8, 8), (12, 10), (9, 13)])
def test_wavelet_layer_matches_pywavelets(wavelet, shape):
    x = np.random.default_rng(0).random((2, *shape))
    want = []
    for im in x:
        approx, _ = pywt.dwt2(im, wavelet, mode="periodization")
        want.append(pywt.idwt2((approx, (None, None, None)), wavelet, mode="periodization")[: shape[0], : shape[1]])
    got = lowpass_projection(torch.from_numpy(x), wavelet).numpy()
    np.testing.assert_allclose(got, np.array(want), atol=1e-12)


def test_feature_order_and_names(base):
    assert len(FEATURE_NAMES) == 26 and FEATURE_NAMES[0] == "mean_01" and FEATURE_NAMES[13] == "std_01"
    # Smoothing kernels sum to 1: every conv noise map has zero mean; stds grow with depth.
    x = torch.rand(4, 1, 32, 32, generator=torch.Generator().manual_seed(2)) * 100
    f = base(x)
    assert torch.all(f[:, :12].abs() < 1e-3)
    assert torch.all(torch.diff(f[:, 13:25], dim=1) >= -1e-4)


def test_std_features_grow_with_noise(base):
    rng = np.random.default_rng(3)
    clean = np.tile(np.linspace(0.1, 0.6, 64, dtype=np.float32)[None, :, None], (64, 1, 3))
    blocks = np.stack([np.clip(clean + s * rng.standard_normal(clean.shape).astype(np.float32), 0, None)
                       for s in (0.0, 0.01, 0.05, 0.2)])
    f = extract_features(blocks, base=base)
    assert np.all(np.diff(f[:, 13:], axis=0) > 0), "noisier blocks must have larger noise stds"


# --- display transform -------------------------------------------------------------
def test_srgb_roundtrip_and_known_lightness():
    v = torch.linspace(0, 1, 1001)
    assert torch.allclose(srgb_decode(srgb_encode(v)), v, atol=1e-6)
    rgb = torch.tensor([[[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.18, 0.18, 0.18]]]])
    L = lightness(rgb)[0, 0]
    assert L[0].item() == pytest.approx(0.0, abs=1e-4)
    assert L[1].item() == pytest.approx(100.0, abs=1e-3)
    assert L[2].item() == pytest.approx(49.496, abs=0.01)   # CIE L* of 18 % grey


def test_lightness_equals_lab_of_display_referred_pixels():
    rgb = torch.rand(2, 8, 8, 3, generator=torch.Generator().manual_seed(4)) * 3
    shown = display(rgb)                                     # sRGB-encoded, in [0, 1]
    lin = srgb_decode(shown)
    y = (lin * torch.tensor([0.2126, 0.7152, 0.0722])).sum(-1)
    d = 6 / 29
    f = torch.where(y > d ** 3, y ** (1 / 3), y / (3 * d * d) + 4 / 29)
    assert torch.allclose(lightness(rgb), 116 * f - 16, atol=1e-3)


def test_exposure_scales_before_clipping():
    rgb = torch.full((1, 8, 8, 3), 0.25)
    assert torch.allclose(lightness(rgb, exposure=2.0), torch.full((1, 8, 8), 100.0), atol=1e-3)


# --- blocks ------------------------------------------------------------------------
def test_split_blocks_row_major_and_roundtrip():
    img = np.arange(8 * 12 * 3, dtype=np.float32).reshape(8, 12, 3)
    b = split_blocks(img, (2, 3))
    assert b.shape == (6, 4, 4, 3)
    np.testing.assert_array_equal(b[1], img[0:4, 4:8])      # row-major: block 1 is top row, 2nd
    np.testing.assert_array_equal(b[3], img[4:8, 0:4])
    np.testing.assert_array_equal(merge_blocks(b, (2, 3)), img)


def test_split_blocks_rejects_uneven_grid():
    with pytest.raises(ValueError, match="cannot be cut"):
        split_blocks(np.zeros((10, 12, 3)), (4, 4))


# --- extremes ----------------------------------------------------------------------
def finite(a) -> bool:
    return bool(np.all(np.isfinite(np.asarray(a))))


def test_black_and_constant_blocks_have_zero_noise(base):
    blocks = np.zeros((3, 16, 16, 3), np.float32)
    blocks[1] = 0.3
    blocks[2] = 50.0          # constant and over-exposed: display clips it to white
    f = extract_features(blocks, base=base)
    assert finite(f)
    np.testing.assert_array_equal(f, np.zeros_like(f))


def test_fireflies_stay_finite_and_bounded(base):
    rng = np.random.default_rng(5)
    blocks = rng.random((2, 32, 32, 3)).astype(np.float32) * 0.2
    blocks[1, ::7, ::5] = 1e6
    f = extract_features(blocks, base=base)
    assert finite(f)
    assert f[1, 13:].max() <= 100.0      # L* is bounded by 100, so is any noise std


def test_nonfinite_pixels_are_counted_not_spread(base):
    rng = np.random.default_rng(6)
    blocks = rng.random((3, 16, 16, 3)).astype(np.float32)
    clean = blocks.copy()
    blocks[1, 3, 4, 0] = np.nan
    blocks[1, 5, 5, :] = -np.inf
    blocks[2, 0, 0, 2] = np.inf
    f, bad = extract_features(blocks, base=base, return_nonfinite=True)
    assert finite(f)
    assert bad.tolist() == [0, 2, 1]
    want = clean.copy()
    want[1, 3, 4, 0] = 0.0
    want[1, 5, 5, :] = 0.0
    want[2, 0, 0, 2] = 1.0
    np.testing.assert_allclose(f, extract_features(want, base=base), rtol=1e-6, atol=1e-6)


def test_float16_input_matches_float32(base):
    rng = np.random.default_rng(7)
    b16 = (rng.random((2, 16, 16, 3)) * 0.8).astype(np.float16)
    np.testing.assert_allclose(extract_features(b16, base=base),
                               extract_features(b16.astype(np.float32), base=base), rtol=1e-6)


@pytest.mark.parametrize("size", [8, 1024])
def test_smallest_and_largest_blocks(base, size):
    rng = np.random.default_rng(8)
    f = extract_features(rng.random((1, size, size, 3)).astype(np.float32), base=base)
    assert f.shape == (1, 26) and finite(f) and f[0, 13:].min() > 0


def test_too_small_or_malformed_blocks_are_rejected(base):
    with pytest.raises(ValueError, match="at least 8x8"):
        extract_features(np.zeros((1, 7, 8, 3), np.float32), base=base)
    with pytest.raises(ValueError, match=r"\[N, H, W, 3\]"):
        extract_features(np.zeros((8, 8, 3), np.float32), base=base)
    with pytest.raises(ValueError, match="floating-point"):
        extract_features(np.zeros((1, 8, 8, 3), np.uint8), base=base)
    with pytest.raises(ValueError, match=r"\[N, 1, H, W\]"):
        base(torch.zeros(2, 3, 8, 8))


def test_empty_batch(base):
    f = extract_features(np.zeros((0, 16, 16, 3), np.float32), base=base)
    assert f.shape == (0, 26)


def test_batch_of_one_equals_batch_of_101_and_calls_repeat(base):
    rng = np.random.default_rng(9)
    blocks = rng.random((101, 32, 32, 3)).astype(np.float32)
    full = extract_features(blocks, base=base)
    again = extract_features(blocks, base=base)
    np.testing.assert_array_equal(full, again)
    for i in (0, 50, 100):
        np.testing.assert_allclose(extract_features(blocks[i:i + 1], base=base)[0], full[i],
                                   rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("scale", [1e-30, 1e-6, 1e6, 1e30])
def test_feature_base_is_scale_equivariant_at_extreme_magnitudes(base, scale):
    x = torch.rand(2, 1, 16, 16, generator=torch.Generator().manual_seed(10))
    f1, fs = base(x), base(x * scale)
    assert torch.isfinite(fs).all()
    np.testing.assert_allclose(fs.numpy(), f1.numpy() * scale, rtol=1e-4, atol=1e-4 * scale)


def test_feature_base_maps_nonfinite_to_zero(base):
    x = torch.rand(1, 1, 16, 16)
    y = x.clone()
    y[0, 0, 2, 2] = float("nan")
    y[0, 0, 3, 3] = float("inf")
    x[0, 0, 2, 2] = 0.0
    x[0, 0, 3, 3] = 0.0
    assert torch.equal(base(y), base(x))


@settings(max_examples=40, deadline=None)
@given(h=st.integers(8, 40), w=st.integers(8, 40), n=st.integers(1, 3),
       mag=st.sampled_from([0.0, 1e-20, 1.0, 1e3, 1e6, 1e20]),
       seed=st.integers(0, 2 ** 31 - 1))
def test_any_shape_any_magnitude_gives_finite_features(base, h, w, n, mag, seed):
    rng = np.random.default_rng(seed)
    blocks = (rng.random((n, h, w, 3)) * mag).astype(np.float32)
    f = extract_features(blocks, base=base)
    assert f.shape == (n, 26) and finite(f)
    assert np.all(f[:, 13:] >= 0) and np.all(f[:, 13:] <= 100.0 + 1e-3)


# --- weights -----------------------------------------------------------------------
def test_weights_roundtrip_and_hash(tmp_path):
    kernels = smoothing_kernels()
    kernels[0] = kernels[0] * 1.5
    path = tmp_path / "w.safetensors"
    save_kernels(path, kernels, {"init": "test"})
    loaded, name = load_kernels(path)
    assert name == "w.safetensors"
    assert all(torch.equal(a, b) for a, b in zip(loaded, kernels))
    assert FeatureBase(path).hash != FeatureBase().hash
    assert FeatureBase().hash == FeatureBase().hash


def test_bad_weight_files_are_rejected(tmp_path):
    with pytest.raises(FileNotFoundError):
        FeatureBase(tmp_path / "missing.safetensors")
    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(b"not a safetensors file")
    with pytest.raises(ValueError, match="not a readable safetensors"):
        FeatureBase(junk)
    short = tmp_path / "short.safetensors"
    save_kernels(short, smoothing_kernels()[:5], {})
    with pytest.raises(ValueError, match="missing tensor"):
        FeatureBase(short)
