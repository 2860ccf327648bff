"""The `halves` model input: what the half buffers say about a block's noise.

The paper's input, features(quick) - features(current), asks the quick image to cancel the
scene content out of the current image's features. On scenes it was not trained on it did
not: edges and texture read as noise, faint noise on smooth shading as nothing. Two half
buffers (A: mean of the even passes, B: mean of the odd ones) are two independent
estimates of one image, so their difference holds noise and no content. From them:

* `n`: the noise image N = L*(display(A)) - L*(display(B)) through the FeatureBase: the
  13 std-pooled features (mean features of a zero-mean image carry nothing), log10;
* `c`: the current image C = (A + B) / 2 through the FeatureBase, the same 13 features,
  log10: how much texture and shading there is to hide noise (masking);
* `r`: the ratios n / c, as log10(n) - log10(c): noise against the content that masks it;
* `l`: the block's mean L* of C, / 100: how bright the block is (noise of one L* amplitude
  is less visible on bright surfaces in FLIP's model);
* `p`: log10 of `noisefeat.perceptual.pooled_colour_error(A, B)`, FLIP's colour pipeline
  in separable filters: what the std features miss (chroma noise, and FLIP's concave
  pooling, which weighs a few fireflies less than spread grain), at a fraction of its cost;
* `f`: log10 of the half-buffer FLIP value e (`learning.inputs.halves.halves_flip`, pooled as
  the observer pools: the largest 16x16 tile mean), the
  `flip` criterion's score: FLIP's perceptual model of the noise, computed for all blocks
  at once by `noisefeat.flip` (the same figure as flip-evaluator to float32 rounding).

Logs, because noise falls as 1/sqrt(spp) and a radial-basis SVM compares distances: in
log scale equal ratios of noise are equal steps whatever the exposure. `COMPOSITIONS`
names the combinations `noisestop bench inputs` measures on held-out scenes; `HALVES` is
the one the `halves` input uses (docs/guide/training.md gives the measurements behind it).

Every route (the tables of stored stacks, the render loop, the server given `even` and
`odd`) builds the input here from the two half buffers, so all judge the same numbers.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from noisefeat import FeatureBase, default_base, fused
from noisefeat.base import N_FEATURES
from noisefeat.bounds import SizeBounds
from noisefeat.display import check_exposure, lightness
from noisefeat.fused import RGBStats
from noisefeat.perceptual import pooled_colour_error

from .halves import check_halves, halves_flip

#: std-pooling columns of the 26 features (FeatureBase order: 13 means, then 13 stds)
STD_COLUMNS = np.arange(N_FEATURES // 2, N_FEATURES)
#: columns of `halves_raw`: N's 26 features, C's 26, C's mean L*, the pooled colour error
RAW_COLUMNS = 2 * N_FEATURES + 2
LUMINANCE, PERCEPTUAL = RAW_COLUMNS - 2, RAW_COLUMNS - 1
#: bumped whenever `halves_raw` computes anything differently: stored stacks' cached
#: copies of older versions are then recomputed, never read
RAW_VERSION = 2
#: floors of the logs: L* spreads below 1e-3 are far below one 8-bit level; FLIP below 1e-4
FEATURE_FLOOR, FLIP_FLOOR = 1e-3, 1e-4
PARTS = {"n": len(STD_COLUMNS), "c": len(STD_COLUMNS), "r": len(STD_COLUMNS), "l": 1, "p": 1, "f": 1}
#: candidate compositions (parts joined by '+'), measured by `noisestop bench inputs`
COMPOSITIONS = ("n", "n+c", "n+r", "n+c+l", "p", "p+l", "p+n+l", "p+c+l", "p+n+c+l", "f", "f+p+n+c+l")
#: the composition of the `halves` input
HALVES = "f"


def parts_of(composition: str) -> list[str]:
    parts = composition.split("+")
    if not parts or any(p not in PARTS for p in parts) or len(set(parts)) != len(parts):
        raise ValueError(f"unknown input composition {composition!r}: parts {'/'.join(PARTS)} joined by '+'")
    return parts


def n_inputs(composition: str = HALVES) -> int:
    return sum(PARTS[p] for p in parts_of(composition))


def _check_halves(even: np.ndarray, odd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, b = check_halves(even, odd)
    # the block bounds of every other model input (noisefeat.bounds), whichever parts are computed
    SizeBounds.from_env().check_block(a.shape[1], a.shape[2], "half-buffer blocks")
    return a, b


def halves_mean(even: np.ndarray, odd: np.ndarray) -> np.ndarray:
    """The current image C = (A + B) / 2 that a `halves` model judges (flat test included);
    a pixel not finite in one half counts as 0 there."""
    a, b = (np.where(np.isfinite(x).all(axis=-1, keepdims=True), x, 0.0) for x in (even, odd))
    return ((a + b) * 0.5).astype(np.result_type(even, odd, np.float32))


def halves_raw(even: np.ndarray, odd: np.ndarray, exposure: float = 0.0,
               base: FeatureBase | None = None) -> np.ndarray:
    """float32 [N, 54]: the 26 features of the noise image N, the 26 of the current image
    C, C's mean L* and the pooled colour error of A against B. Non-finite pixels follow
    the display rule (NaN/-Inf black, +Inf white).

    N and C come from the fused path (`noisefeat.fused.halves_features`): L* of A and of B
    once each, both images through one spectral call per chunk of blocks."""
    return halves_analysis(even, odd, exposure, base)[0]


def halves_analysis(even: np.ndarray, odd: np.ndarray, exposure: float = 0.0,
                    base: FeatureBase | None = None, display_range: bool = False,
                    colour: bool = True) -> tuple[np.ndarray, RGBStats]:
    """(`halves_raw` rows, RGBStats: non-finite pixels of A plus B, C's display range if
    asked) from one fused pass; `colour=False` leaves the pooled colour error column 0 (a
    composition without the `p` part does not read it)."""
    a, b = _check_halves(even, odd)
    if not np.isfinite(exposure):
        raise ValueError(f"exposure must be finite, got {exposure}")
    exposure = check_exposure(exposure)
    base = base or default_base()
    with torch.inference_mode():
        noise, current, mean_l, stats = fused.halves_features(torch.as_tensor(a), torch.as_tensor(b), exposure,
                                                              base, with_range=display_range)
        colour_err = pooled_colour_error(a, b, exposure) if colour and len(a) else torch.zeros(len(a))
        out = torch.cat([noise, current, mean_l[:, None], colour_err[:, None]], dim=1)
    return out.numpy().astype(np.float32), stats


def compose(raw: np.ndarray | None, flip: np.ndarray | None, composition: str = HALVES) -> np.ndarray:
    """Model inputs [N, n_inputs] from `halves_raw` rows and FLIP values e (either may be
    None when the composition does not use it). e that is NaN (not measured: flat blocks,
    whose verdict the stop rule gives without the model) reads as the floor."""
    cols = []
    for p in parts_of(composition):
        if p == "f":
            if flip is None:
                raise ValueError(f"composition {composition!r} needs the FLIP values")
            e = np.nan_to_num(np.asarray(flip, np.float64), nan=FLIP_FLOOR, posinf=1.0, neginf=FLIP_FLOOR)
            cols.append(np.log10(np.clip(e, FLIP_FLOOR, 1.0))[:, None])
            continue
        if raw is None:
            raise ValueError(f"composition {composition!r} needs the half-buffer features")
        raw = np.asarray(raw, np.float64)
        if raw.ndim != 2 or raw.shape[1] != RAW_COLUMNS:
            raise ValueError(f"expected halves features [N, {RAW_COLUMNS}], got shape {raw.shape}")
        if p == "l":
            cols.append(raw[:, LUMINANCE:LUMINANCE + 1] / 100.0)
        elif p == "p":
            cols.append(np.log10(np.clip(raw[:, PERCEPTUAL:PERCEPTUAL + 1], FLIP_FLOOR, 1.0)))
        else:
            n = np.log10(np.maximum(raw[:, STD_COLUMNS], FEATURE_FLOOR))
            c = np.log10(np.maximum(raw[:, N_FEATURES + STD_COLUMNS], FEATURE_FLOOR))
            cols.append({"n": n, "c": c, "r": n - c}[p])
    return np.concatenate(cols, axis=1).astype(np.float32)


def needs(composition: str) -> tuple[bool, bool]:
    """(needs the FeatureBase features, needs FLIP) of a composition."""
    parts = parts_of(composition)
    return any(p != "f" for p in parts), "f" in parts


def halves_input(even: np.ndarray, odd: np.ndarray, exposure: float = 0.0,
                 base: FeatureBase | None = None, composition: str = HALVES) -> np.ndarray:
    """The `halves` model input [N, n_inputs] of N blocks' half buffers (render loop, server)."""
    return halves_input_and_stats(even, odd, exposure, base, composition)[0]


def halves_input_and_stats(even: np.ndarray, odd: np.ndarray, exposure: float = 0.0,
                           base: FeatureBase | None = None, composition: str = HALVES
                           ) -> tuple[np.ndarray, RGBStats]:
    """(`halves_input`, RGBStats of the half buffers: non-finite pixels of A plus B, and
    the display range of C = (A + B) / 2 for the flat-block test), the statistics from the
    same fused pass as the features (or from a pass of their own when the composition
    reads none)."""
    a, b = _check_halves(even, odd)
    if not np.isfinite(exposure):
        raise ValueError(f"exposure must be finite, got {exposure}")
    exposure = check_exposure(exposure)
    feats, flip = needs(composition)
    if feats:
        raw, stats = halves_analysis(a, b, exposure, base, display_range=True,
                                     colour="p" in parts_of(composition))
    else:
        raw = None
        with torch.inference_mode():
            stats = fused.halves_stats(torch.as_tensor(a), torch.as_tensor(b), exposure)
    x = compose(raw, halves_flip(a, b, exposure) if flip and len(a) else (np.zeros(0) if flip else None),
                composition)
    return x, stats


def noise_lightness(even: np.ndarray, odd: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """float32 [N, h*w]: the noise image (L*(display(A)) - L*(display(B))) / 100, flattened:
    the raw-pixel SVM's `halves` input, as the raw L*/100 block is its paper input."""
    a, b = _check_halves(even, odd)
    if not np.isfinite(exposure):
        raise ValueError(f"exposure must be finite, got {exposure}")
    with torch.inference_mode():
        n = lightness(torch.as_tensor(a), exposure) - lightness(torch.as_tensor(b), exposure)
    return (n / 100.0).reshape(len(a), -1).numpy().astype(np.float32)


def layout(composition: str = HALVES) -> Sequence[str]:
    """Column names of a composition, for manifests and reports."""
    names = {"f": ["log10 flip(A, B)"],
             "n": [f"log10 std noise layer {i + 1}" for i in range(len(STD_COLUMNS))],
             "c": [f"log10 std current layer {i + 1}" for i in range(len(STD_COLUMNS))],
             "r": [f"log10 std ratio noise / current layer {i + 1}" for i in range(len(STD_COLUMNS))],
             "l": ["mean L* of current / 100"], "p": ["log10 pooled colour error(A, B)"]}
    return [n for p in parts_of(composition) for n in names[p]]
