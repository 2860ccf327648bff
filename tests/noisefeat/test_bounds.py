"""Resource bounds: operators linear in the block size, bounded caches, size ceilings."""
from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
import torch

from noisefeat import FeatureBase, extract_features
from noisefeat.bounds import MIN_SIDE, SizeBounds
from noisefeat.cache import ByteLRU, default_max_bytes
from noisefeat.wavelet import _dense_taps, _taps


@pytest.mark.parametrize("wavelet", ["haar", "db2", "db4", "sym5", "bior2.2", "coif3"])
def test_wrapped_taps_equal_the_dense_reading_at_every_size(wavelet):
    for n in range(2, 202, 2):
        _taps.cache_clear()
        got, want = _taps(wavelet, n), _dense_taps(wavelet, n)
        for g, w in zip(got, want):
            assert [m for m, _ in g] == [m for m, _ in w], (wavelet, n)
            np.testing.assert_allclose([x for _, x in g], [x for _, x in w], atol=1e-12)


def test_tap_construction_allocates_nothing_like_n_squared():
    """An 8000-wide block used to take an 8000 x 8000 identity (512 MB) to read its taps."""
    _taps.cache_clear()
    tracemalloc.start()
    try:
        _taps("db4", 8000)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 1_000_000, peak


def test_wide_thin_block_is_featured_and_wrapped_route_matches_conv2d():
    base = FeatureBase(wavelet="db4").eval()
    x = torch.rand(2, 1, 8, 6000, generator=torch.Generator().manual_seed(0)) * 100
    with torch.no_grad():
        feats = base(x)
    assert feats.shape == (2, 26) and torch.isfinite(feats).all()
    small = torch.rand(2, 1, 40, 64, generator=torch.Generator().manual_seed(1)) * 100
    with torch.no_grad():
        fast = base(small)
        outs = [o.double() for o in base.layer_outputs(small.double())]
    slow_std = torch.stack([(small.double() - o)[:, 0].std((-2, -1), correction=0) for o in outs], 1)
    np.testing.assert_allclose(fast[:, 13:].numpy(), slow_std.float().numpy(), rtol=1e-4, atol=2e-4)


def test_byte_lru_evicts_oldest_and_refuses_what_cannot_fit():
    cache = ByteLRU(max_bytes=3000)
    for k in range(5):
        cache.put(k, torch.zeros(250))           # 1000 bytes each
    assert cache.bytes <= 3000 and len(cache) == 3 and 0 not in cache and 4 in cache
    cache.get(2)                                  # 2 is now the most recent
    cache.put(9, torch.zeros(250))
    assert 2 in cache and 3 not in cache
    too_big = torch.zeros(1000)
    assert cache.put("big", too_big) is too_big and "big" not in cache
    cache.clear()
    assert cache.bytes == 0 and len(cache) == 0
    with pytest.raises(ValueError, match="max_bytes"):
        ByteLRU(-1)


def test_feature_base_operator_cache_stays_within_its_budget():
    budget = 4_000_000
    base = FeatureBase(operator_cache_bytes=budget).eval()
    for side in range(64, 200, 8):               # 17 distinct sizes of ~0.3-3 MB of operators
        extract_features(np.random.default_rng(side).random((1, side, side + 2, 3), np.float32), base=base)
        assert base._transfer_cache.bytes <= budget
    assert (192, 194) in base._transfer_cache    # the latest size is kept
    assert len(base._transfer_cache) < 17


def test_operator_cache_budget_from_the_environment():
    assert default_max_bytes({}) == 256 * 1024 * 1024
    assert default_max_bytes({"NOISESTOP_OPERATOR_CACHE_BYTES": "1000"}) == 1000
    with pytest.raises(ValueError, match="NOISESTOP_OPERATOR_CACHE_BYTES"):
        default_max_bytes({"NOISESTOP_OPERATOR_CACHE_BYTES": "lots"})


def test_size_bounds_name_the_bound_they_hit():
    b = SizeBounds(max_block_side=256, max_pixels=100_000, max_frame_pixels=1_000_000)
    b.check_request(1, 256, 256)
    with pytest.raises(ValueError, match="max_block_side = 256"):
        b.check_request(1, 8, 40000)
    with pytest.raises(ValueError, match="max_pixels = 100000"):
        b.check_request(2, 256, 256)
    with pytest.raises(ValueError, match=f"at least {MIN_SIDE}x{MIN_SIDE}"):
        b.check_frame(64, 64, (64, 64))              # 1-pixel blocks
    with pytest.raises(ValueError, match="max_frame_pixels"):
        b.check_frame(2000, 2000, (10, 10))
    assert SizeBounds.from_env({"NOISESTOP_MAX_BLOCK_SIDE": "512"}).max_block_side == 512
    assert SizeBounds.from_env({"NOISESTOP_MAX_BLOCK_SIDE": "512"}, max_block_side=64).max_block_side == 64
    for bad in ({"NOISESTOP_MAX_PIXELS": "many"}, {"NOISESTOP_MAX_PIXELS": "4"}):
        with pytest.raises(ValueError, match="max_pixels|NOISESTOP_MAX_PIXELS"):
            SizeBounds.from_env(bad)


@pytest.mark.parametrize("raw,zero,want", [
    (None, False, 7.0), ("  ", False, 7.0), ("5", False, 5.0), ("3600", False, 3600.0), ("0", True, 0.0),
    ("0", False, None), ("3600.5", False, None), ("-1", False, None), ("nan", False, None), ("inf", False, None),
    ("1e999", False, None), ("abc", False, None)])
def test_env_seconds_is_the_one_parser_of_time_settings(raw, zero, want):
    """Unset or blank: the default; else a number of seconds in (0, most] ([0, most] with
    zero), or one error line naming the variable and the range."""
    from noisefeat.bounds import env_seconds

    environ = {} if raw is None else {"NOISESTOP_X": raw}
    if want is not None:
        assert env_seconds(environ, "NOISESTOP_X", 7.0, 3600, zero=zero) == want
        return
    with pytest.raises(ValueError, match=r"NOISESTOP_X must be a number of seconds in \(0, 3600\], got"):
        env_seconds(environ, "NOISESTOP_X", 7.0, 3600, zero=zero)


def test_no_noisestop_number_is_parsed_outside_bounds():
    """One parser of NOISESTOP_* numbers (`env_int`, `env_seconds`): no product module turns
    an environment value into a number itself."""
    import re

    from tests.support import ROOT

    found = []
    for pkg in ("noisefeat", "learning", "renderer", "service"):
        for p in sorted((ROOT / pkg).rglob("*.py")):
            if p.name == "bounds.py":
                continue
            text = p.read_text()
            names = re.findall(r"(\w+) = (?:os\.)?environ\.get\(", text)       # values read from the env
            conv = re.compile(r"\b(?:int|float)\(\s*(?:(?:os\.)?environ\b" + "".join(f"|{n}\\b" for n in names) + ")")
            found += [f"{p.relative_to(ROOT)}:{i}" for i, line in enumerate(text.splitlines(), 1) if conv.search(line)]
    assert found == []
