"""The virtual observer: display rule, FLIP wrapper, block errors, thresholds."""
from __future__ import annotations

import numpy as np
import pytest

from learning.data.block_terms import block_errors, pooled_errors, stack_observer_errors
from learning.data.frame_flip import display, flip_map, srgb_decode
from learning.data.observer import VirtualObserver, label_stack, thresholds_from_errors
from learning.data.relabel import observed, read_observed, relabel_if_stale
from learning.data.stack import read_stack
from learning.data.stack_write import update_labels
from noisefeat.dots import OBSERVER_DOTS
from noisefeat.pooling import POOLINGS, pool_blocks
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

@pytest.mark.parametrize("pooling", ["tile16-max", "mean"])
def test_block_pooling_row_major(pooling):
    m = np.kron(np.arange(6, dtype=np.float64).reshape(2, 3), np.ones((40, 50)))
    np.testing.assert_array_equal(pool_blocks(m, (2, 3), pooling), np.arange(6))


def test_noise_in_one_tile_is_diluted_by_the_mean_but_not_by_tile_pooling():
    """Grain in one corner of a 64x64 block beside a clean rest: the first observer's mean
    divides it by the 16 tiles, the tile pooling keeps it."""
    ref = np.full((64, 64, 3), 0.18, np.float32)
    lev = ref.copy()
    lev[:16, :16] *= np.random.default_rng(0).lognormal(0, 0.6, (16, 16, 1)).astype(np.float32)
    e = pooled_errors(ref, [lev], (1, 1))
    tile, mean = e[POOLINGS.index("tile16-max"), 0, 0], e[POOLINGS.index("mean"), 0, 0]
    assert tile > 0.05 and 10 < tile / mean <= 16      # the noisy tile (FLIP spreads a little past it)
    obs = VirtualObserver()
    assert obs.thresholds(ref, [lev, ref], [8, 16], (1, 1)) == [16]
    assert VirtualObserver(pooling="mean").thresholds(ref, [lev, ref], [8, 16], (1, 1)) == [8]


def test_identical_levels_give_zero_error_and_first_level_thresholds():
    ref = np.random.default_rng(0).random((32, 32, 3)).astype(np.float32) * 3  # HDR
    e = block_errors(ref, [ref, ref, ref])
    assert e.shape == (3, 16) and float(np.abs(e).max()) == 0.0
    assert pooled_errors(ref, [ref]).shape == (len(POOLINGS), 1, 16)
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
    strict = label_stack(st, tau=1e-9)
    assert all(t is None for t in strict)


def test_virtual_observer_settings():
    obs = VirtualObserver(tau=0.03, ppd=40)
    assert obs.labeler == {"name": "flip", "tau": 0.03, "ppd": 40, "display": "clip+srgb",
                           "exposure": 0.0, "pooling": "tile16-max+dots", **OBSERVER_DOTS, "tile_truth": "final-frame"}
    assert VirtualObserver(pooling="mean").labeler["pooling"] == "mean"
    assert VirtualObserver(pooling="tile16-max").labeler["pooling"] == "tile16-max"
    for bad in (-1, 0, float("nan"), float("inf"), "x"):
        with pytest.raises(ValueError, match="tau"):
            VirtualObserver(tau=bad)
    with pytest.raises(ValueError, match="ppd"):
        VirtualObserver(ppd=0)
    with pytest.raises(ValueError, match="unknown pooling 'max'"):
        VirtualObserver(pooling="max")


def _mean_labelled(tmp_path, size=128):
    """A stack of 2x2 blocks of 64x64 labelled as the first observer did: no "pooling" key."""
    st = make_synthetic_stack(tmp_path / "s", size=size, grid=(2, 2), spp=[16, 64, 256, 1024, 4096])
    v1 = {k: v for k, v in st.labeler.items() if k != "pooling"}
    return update_labels(st, label_stack(st, pooling="mean"), v1)


def test_a_stack_without_pooling_counts_as_mean_labelled_and_is_relabelled_never_misread(tmp_path):
    st = _mean_labelled(tmp_path)
    mean_th, tile_th = label_stack(st, pooling="mean"), label_stack(st)
    assert st.thresholds == mean_th and tile_th != mean_th         # the two observers differ here
    big = 10 ** 9
    assert all((big if t is None else t) >= (big if m is None else m) for t, m in zip(tile_th, mean_th))
    seen = observed(st)                                            # in memory: tile labels
    assert seen.thresholds == tile_th and seen.labeler["pooling"] == "tile16-max+dots"
    assert read_stack(st.path).thresholds == mean_th               # meta.json untouched
    assert observed(st, pooling="mean").thresholds == mean_th      # still selectable
    assert [s.thresholds for s in read_observed(str(tmp_path))] == [tile_th]
    assert observed(st, tau=0.05).thresholds == label_stack(st, tau=0.05)


def test_relabelling_reads_cached_errors_and_never_renders(tmp_path, monkeypatch):
    st = _mean_labelled(tmp_path)
    e = stack_observer_errors(st)                                  # computed once, cached
    assert e.shape == (len(POOLINGS), 5, 4)
    import learning.data.frame_flip as flip_mod
    monkeypatch.setattr(flip_mod, "flip_map", lambda *a, **k: (_ for _ in ()).throw(AssertionError("FLIP ran")))
    for tau in (0.01, 0.02, 0.04):
        observed(st, tau)
    np.testing.assert_array_equal(stack_observer_errors(st), e)


def test_unknown_pooling_in_a_stack_is_refused_with_one_line(tmp_path):
    st = _mean_labelled(tmp_path)
    meta = st.path / "meta.json"
    import json
    m = json.loads(meta.read_text())
    m["labeler"]["pooling"] = "p99"
    meta.write_text(json.dumps(m))
    with pytest.raises(ValueError, match="labeler pooling 'p99' is unknown") as err:
        read_stack(st.path)
    assert "\n" not in str(err.value)


def test_relabel_if_stale_updates_flip_labels_and_keeps_human_ones(tmp_path):
    st = _mean_labelled(tmp_path)
    again, did = relabel_if_stale(read_stack(st.path))
    assert did and again.labeler == VirtualObserver().labeler and again.thresholds == label_stack(st)
    assert relabel_if_stale(again) == (again, False)               # current labeler: untouched
    back, did = relabel_if_stale(again, pooling="mean")
    assert did and back.labeler["pooling"] == "mean"
    human = update_labels(again, [16] * 4, {"name": "human", "source": "LISIC"})
    assert relabel_if_stale(human) == (human, False)
    assert observed(human, tau=0.01) is human                       # human labels are the data


def _dotted(n_dots: int, value: float = 0.005, size: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """A black reference and a level holding `n_dots` single pixels on it, spread apart
    (linear 0.005: display 0.061, over the 0.03 a dot needs at tau 0.02)."""
    ref = np.zeros((size, size, 3), np.float32)
    lev = ref.copy()
    ys, xs = np.unravel_index(np.random.default_rng(1).choice(size * size // 4, n_dots, replace=False),
                              (size // 2, size // 2))
    lev[2 * ys, 2 * xs] = value
    return ref, lev


@pytest.mark.parametrize("n_dots,v3_converged", [(0, True), (8, True), (16, True), (17, False), (60, False)])
def test_version_3_refuses_dots_on_black_that_the_tile_mean_blurs_away(n_dots, v3_converged):
    """Single light pixels on black at 1:1. FLIP's 16x16 tile mean stays under tau
    with sixty of them; the dot term lets at most 16 of a 64x64 block through."""
    ref, lev = _dotted(n_dots)
    e = pooled_errors(ref, [lev], (1, 1))[:, 0, 0]
    assert e[POOLINGS.index("tile16-max")] <= 0.02                 # version 2 calls it converged
    assert (e[POOLINGS.index("tile16-max+dots")] <= 0.02) == v3_converged
    assert VirtualObserver().thresholds(ref, [lev, ref], [8, 16], (1, 1)) == [8 if v3_converged else 16]
    assert VirtualObserver(pooling="tile16-max").thresholds(ref, [lev, ref], [8, 16], (1, 1)) == [8]


def test_the_dot_level_follows_tau():
    """A dot is an outlier at 1.5 tau: a stricter target sees fainter dots."""
    ref, lev = _dotted(30, value=0.002)           # display 0.026 each: under 0.03, over 0.0225
    e = pooled_errors(ref, [lev], (1, 1))[:, 0, 0]
    assert e[POOLINGS.index("tile16-max")] < 0.01
    e = e[POOLINGS.index("tile16-max+dots")]
    assert thresholds_from_errors(np.array([[e]]), [8], 0.02) == [8]
    assert thresholds_from_errors(np.array([[e]]), [8], 0.015) == [None]


def test_a_version_2_stack_is_relabelled_by_its_dot_term_alone(tmp_path, monkeypatch):
    """Stacks labelled before version 3 keep their cached FLIP errors: relabelling reads the
    levels for the dot term only, never FLIP (the tile truth's FLIP terms and its final-frame
    fixed point are cached apart, made once)."""
    from learning.data.observer import observer_for
    from learning.data.tile_terms import stack_tile_errors

    st = make_synthetic_stack(tmp_path / "s", size=128, grid=(2, 2), spp=[16, 64, 256, 1024])
    st = update_labels(st, label_stack(st, pooling="tile16-max"), {**st.labeler, "pooling": "tile16-max"})
    stack_observer_errors(st)
    stack_tile_errors(st)
    observer_for(st).label_tiles(st)
    for f in (st.path / ".cache").glob("observer-dots-*"):
        f.unlink()
    import learning.data.frame_flip as flip_mod
    monkeypatch.setattr(flip_mod, "flip_map", lambda *a, **k: (_ for _ in ()).throw(AssertionError("FLIP ran")))
    new, relabelled = relabel_if_stale(read_stack(st.path))
    assert relabelled and new.labeler["pooling"] == "tile16-max+dots"
    assert list(st.path.joinpath(".cache").glob("observer-dots-*"))


def test_labels_of_other_dot_settings_are_relabelled_never_read(tmp_path, monkeypatch):
    """The labeler record names the dot level and density: a stack labelled at another
    setting is relabelled like one of another pooling."""
    st = make_synthetic_stack(tmp_path / "s", size=64, spp=[16, 64, 256, 1024])
    assert st.labeler["dot_level"] == OBSERVER_DOTS["dot_level"]
    other = update_labels(st, st.thresholds, {**st.labeler, "dot_level": 9.0})
    assert observed(other).labeler["dot_level"] == OBSERVER_DOTS["dot_level"]
    assert relabel_if_stale(other)[1]
