"""The virtual observer: display rule, FLIP wrapper, block errors, thresholds."""
from __future__ import annotations

import numpy as np
import pytest

from learning.data.observer import (VirtualObserver, block_errors, block_means, display, flip_map,
                                    label_stack, relabel_if_stale, srgb_decode,
                                    thresholds_from_errors)
from learning.data.stack import read_stack, update_labels
from learning.data.synthetic import make_synthetic_stack, synthetic_images

SPP = [4, 8, 16, 32, 64, 128, 256, 512, 1024]


def _srgb(h=32, w=32, seed=0):
    return np.random.default_rng(seed).random((h, w, 3)).astype(np.float32)


# ----------------------------------------------------------------------------- display

def test_display_rule():
    x = np.array([[[0.0, 0.5, 1.0], [2.0, np.nan, -np.inf], [np.inf, -0.3, 0.001]]],
                 dtype=np.float32)
    d = display(x)
    assert d.dtype == np.float32 and d.flags.c_contiguous and d.shape == x.shape
    np.testing.assert_allclose(d[0, 0], [0.0, 0.735357, 1.0], atol=1e-5)
    np.testing.assert_allclose(d[0, 1], [1.0, 0.0, 0.0])        # clip, NaN -> 0, -Inf -> 0
    np.testing.assert_allclose(d[0, 2], [1.0, 0.0, 0.01292], atol=1e-6)  # +Inf -> 1, linear toe
    np.testing.assert_allclose(display(np.full((1, 1, 3), 0.25, np.float32), exposure=1.0),
                               display(np.full((1, 1, 3), 0.5, np.float32)))


def test_srgb_decode_of_mid_grey():
    assert abs(float(srgb_decode(np.float32(0.5))) - 0.21404114) < 1e-6


# ----------------------------------------------------------------------------- FLIP

def test_flip_map_identical_is_zero_and_difference_is_positive():
    a = _srgb()
    m = flip_map(a, a)
    assert m.shape == (32, 32) and m.dtype == np.float32
    assert float(m.max()) == 0.0
    b = np.clip(a + 0.2, 0, 1).astype(np.float32)
    m2 = flip_map(a, b)
    assert 0.0 < float(m2.mean()) <= 1.0
    # ppd is really passed on: viewing from farther (fewer px/deg) changes the map
    assert not np.allclose(flip_map(a, b, ppd=10), m2)


@pytest.mark.parametrize("ref, test, ppd, message", [
    (_srgb(), _srgb(), 0, "ppd"),
    (_srgb(), _srgb(), -5, "ppd"),
    (_srgb(), _srgb(), float("nan"), "ppd"),
    (_srgb(), _srgb(), "far", "ppd"),
    (_srgb(), _srgb(16, 32), 67, "differ in shape"),
    (_srgb() * 2, _srgb(), 67, r"\[0, 1\]"),
    (_srgb() - 0.5, _srgb(), 67, r"\[0, 1\]"),
    (np.full((8, 8, 3), np.nan, np.float32), np.zeros((8, 8, 3), np.float32), 67, "NaN"),
    ((_srgb() * 255).astype(np.uint8), _srgb(), 67, "dtype"),
    (_srgb()[..., 0], _srgb()[..., 0], 67, r"\[H, W, 3\]"),
    (np.zeros((0, 4, 3), np.float32), np.zeros((0, 4, 3), np.float32), 67, "H, W > 0"),
    (_srgb().tolist(), _srgb(), 67, "numpy array"),
])
def test_flip_map_invalid_inputs_raise_value_error_not_exit(ref, test, ppd, message):
    with pytest.raises(ValueError, match=message):
        flip_map(ref, test, ppd=ppd)


def test_flip_systemexit_is_converted(monkeypatch):
    import flip_evaluator

    def boom(*a, **k):
        print("Viewing condition options must be positive.\nExiting.")
        raise SystemExit(1)

    monkeypatch.setattr(flip_evaluator, "evaluate", boom)
    with pytest.raises(ValueError, match="Viewing condition"):
        flip_map(_srgb(), _srgb())


def test_flip_accepts_non_contiguous_float64():
    a = _srgb(16, 16)
    view = np.asfortranarray(a.astype(np.float64))
    np.testing.assert_allclose(flip_map(view, view[:, :, :]), 0.0)


# ----------------------------------------------------------------------------- errors

def test_block_means_row_major():
    m = np.kron(np.arange(6, dtype=np.float64).reshape(2, 3), np.ones((4, 5)))
    np.testing.assert_array_equal(block_means(m, (2, 3)), np.arange(6))


def test_identical_levels_give_zero_error_and_first_level_thresholds():
    ref = np.random.default_rng(0).random((32, 32, 3)).astype(np.float32) * 3  # HDR
    e = block_errors(ref, [ref, ref, ref])
    assert e.shape == (3, 16) and float(np.abs(e).max()) == 0.0
    assert thresholds_from_errors(e, [10, 20, 30]) == [10] * 16
    assert VirtualObserver().thresholds(ref, np.stack([ref, ref]), [5, 9]) == [5] * 16


def test_noise_decreasing_with_spp_gives_monotone_thresholds():
    ref, _, levels = synthetic_images(64, SPP, seed=0, noise=0.15)
    e = block_errors(ref, levels)
    assert e.shape == (len(SPP), 16)
    assert np.all(e[-1] < e[0])                       # error falls with spp, in every block
    assert np.all(np.diff(e.mean(axis=1)) < 0)        # and on average at every step
    th = thresholds_from_errors(e, SPP)
    big = 10 ** 9
    grid = np.array([big if t is None else t for t in th]).reshape(4, 4)
    # noise amplitude grows left to right: thresholds never decrease along a row
    assert np.all(np.diff(grid, axis=1) >= 0)
    assert grid[:, 0].max() < big and grid[:, -1].min() >= 1024   # clean left, noisy right
    # level k converged <=> all later errors <= tau
    for b, t in enumerate(th):
        if t is not None:
            k = SPP.index(t)
            assert np.all(e[k:, b] <= 0.02) and (k == 0 or e[k - 1, b] > 0.02)
        else:
            assert e[-1, b] > 0.02


def test_thresholds_rule_2_non_monotone_censored_and_edge_cases():
    spp = [10, 20, 30, 40, 50]
    per_block = [
        [0.05, 0.01, 0.03, 0.01, 0.01],   # dips below tau at 20, rises at 30, then stays
        [0.05, 0.04, 0.03, 0.02, 0.01],   # reaches exactly tau at 40
        [0.01, 0.01, 0.01, 0.01, 0.01],   # always below tau
        [0.03, 0.03, 0.03, 0.03, 0.03],   # never below tau
        [0.02, 0.02, 0.02, 0.02, np.nan],  # NaN on the last level
    ]
    e = np.array(per_block).T            # e[k, b]
    th = thresholds_from_errors(e, spp, tau=0.02)
    assert th[0] == 40           # dip at 20 ignored, converged from 40 on
    assert th[1] == 40           # exactly tau counts as converged
    assert th[2] == 10           # always below tau
    assert th[3] is None         # never converged: censored
    assert th[4] is None         # NaN error on the last level: not converged
    assert thresholds_from_errors(e, spp, tau=0.05)[:4] == [10, 10, 10, 10]
    with pytest.raises(ValueError, match="spp values"):
        thresholds_from_errors(e, spp[:3])
    with pytest.raises(ValueError, match="strictly increasing"):
        thresholds_from_errors(e, [10, 20, 20, 40, 50])
    with pytest.raises(ValueError, match=r"\[K, n_blocks\]"):
        thresholds_from_errors(e[0], spp)


def test_nan_in_levels_is_handled_by_the_display_rule():
    ref = np.full((32, 32, 3), 0.2, np.float32)
    lev = ref.copy()
    lev[3, 3] = [np.nan, np.inf, -np.inf]          # block 0
    e = block_errors(ref, [lev])
    assert np.all(np.isfinite(e))
    assert e[0, 0] > 0 and np.all(e[0, 1:] < e[0, 0])
    with pytest.raises(ValueError, match="shape"):
        block_errors(ref, [lev[:16]])
    with pytest.raises(ValueError, match="no levels"):
        block_errors(ref, [])


def test_label_stack_matches_stored_thresholds(tmp_path):
    st = make_synthetic_stack(tmp_path / "s", size=64, spp=[16, 64, 256, 1024])
    assert label_stack(st) == st.thresholds
    strict = label_stack(st, tau=0.0)
    assert all(t is None for t in strict)


def test_virtual_observer_settings():
    obs = VirtualObserver(tau=0.03, ppd=40)
    assert obs.labeler == {"name": "flip", "tau": 0.03, "ppd": 40, "display": "clip+srgb",
                           "exposure": 0.0}
    assert VirtualObserver(edge_margin=10).labeler["edge_margin"] == 10
    with pytest.raises(ValueError, match="tau"):
        VirtualObserver(tau=-1)
    with pytest.raises(ValueError, match="ppd"):
        VirtualObserver(ppd=0)


# ----------------------------------------------------------------------------- edge margin

def test_block_means_edge_margin_leaves_out_the_frame_border_only():
    v = np.ones((8, 8))
    v[0, :] = v[-1, :] = v[:, 0] = v[:, -1] = 100.0          # a 1-px frame border
    np.testing.assert_allclose(block_means(v, (2, 2), edge_margin=1), [1.0] * 4)
    assert block_means(v, (2, 2))[0] > 1.0                    # margin 0: the plain mean
    # margin 2 leaves one interior pixel per 4x4 block; margin 4 leaves none -> plain mean
    np.testing.assert_allclose(block_means(v, (2, 2), edge_margin=4), block_means(v, (2, 2)))
    with pytest.raises(ValueError, match="edge_margin"):
        block_means(v, (2, 2), edge_margin=-1)
    with pytest.raises(ValueError, match="edge_margin"):
        VirtualObserver(edge_margin=1.5)


def test_edge_margin_makes_a_block_score_alike_alone_and_inside_a_larger_frame():
    # The same 64x64 content alone and as the centre-left block of a 128x128 frame: with the
    # margin the one-block frame's error is the inner part of the same FLIP field.
    rng = np.random.default_rng(3)
    big_ref = rng.random((128, 128, 3)).astype(np.float32) * 0.5 + 0.25
    big_test = np.clip(big_ref + rng.normal(0, 0.05, big_ref.shape), 0, 1).astype(np.float32)
    crop = (slice(32, 96), slice(0, 64))
    alone = [block_errors(srgb_decode(big_ref[crop]), [srgb_decode(big_test[crop])], (1, 1),
                          edge_margin=m)[0, 0] for m in (0, 10)]
    inner = float(flip_map(big_ref, big_test)[crop][10:-10, 10:-10].mean())   # same pixels, framed
    assert abs(alone[1] - inner) < abs(alone[0] - inner)
    assert abs(alone[1] - inner) / inner < 0.02


def test_relabel_if_stale_updates_flip_labels_and_keeps_human_ones(tmp_path):
    st = make_synthetic_stack(tmp_path / "s", size=64, spp=[16, 64, 256, 1024])
    obs = VirtualObserver()
    assert relabel_if_stale(st, obs) == (st, False)           # current labeler: untouched
    update_labels(st, [None] * 16, VirtualObserver(edge_margin=10).labeler)   # another observer's
    again, did = relabel_if_stale(read_stack(st.path), obs)
    assert did and again.labeler == obs.labeler and again.thresholds == st.thresholds
    human = update_labels(again, [16] * 16, {"name": "human", "source": "LISIC"})
    assert relabel_if_stale(human, obs) == (human, False)
