"""LDR-FLIP for many blocks at once: NVIDIA FLIP's computation, batched in torch on any device.

Why: the `flip` criterion and the bundled model's `halves` input (composition `f`) score a
block by the LDR-FLIP map between display(A) and display(B), its two half buffers, pooled.
`flip-evaluator` computes one image pair per call with direct 21-tap loops: ~4.8 ms per
64x64 block, ~250 ms per service request of 16 blocks of 128x128 (measured). The same
computation as a few large matrix products over every block of a batch costs a small
fraction of that.

What is computed is FLIP's LDR pipeline as `flip-evaluator` 1.7 runs it (FLIP.h of
NVlabs/flip; Andersson et al., HPG 2020), on each block alone:

* colour: linear RGB -> YCxCz (FLIP's RGB->XYZ matrix and D65 white); each channel
  low-passed by its contrast-sensitivity filter (Y, Cx: one Gaussian; Cz: the sum of two,
  separated as FLIP separates them), all of radius ceil(3 sqrt(0.04 / (2 pi^2)) ppd)
  (10 pixels at 67 ppd); back to linear RGB, clamped to [0, 1]; CIELab with the Hunt
  adjustment; HyAB distance ^ 0.7, compressed into [0, 1] with the knee at 0.4 cmax;
* features: the achromatic channel, (Y + 16) / 116, filtered by a Gaussian and its first
  and second derivatives (sigma 0.5 * 0.082 ppd, radius ceil(3 sigma): 9 pixels at 67 ppd,
  each lobe normalised as FLIP does); edge and point magnitudes; the feature difference
  sqrt(max(|d edge|, |d point|) / sqrt 2);
* error = colour ^ (1 - feature), per pixel.

Borders are clamped (the nearest edge pixel is repeated), as FLIP's loops clamp indices.
Each 1D pass is a banded matrix product: the axis is cut into tiles of about 16 pixels,
each tile's window (tile plus the filter radius on both sides, indices clamped) is
gathered once, and one GEMM applies every filter that axis needs. Arithmetic is float32 as
in FLIP; only the order of the sums differs, so maps agree to float32 rounding
(tests/noisefeat/test_flip.py compares the two on realistic and extreme blocks).

`ldr_flip(reference, test)` takes sRGB images in [0, 1] like `flip_evaluator.evaluate`;
`flip_halves(even, odd)` takes linear half buffers, follows the display rule
(noisefeat.display: x 2^exposure, NaN/-Inf black, +Inf white, clip to [0, 1]) and pools
each block's map as the observer does (`noisefeat.pooling`).
"""
from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from functools import lru_cache

import numpy as np
import torch

from .display import clipped_linear, srgb_decode
from .perceptual import DEFAULT_PPD, PC, PT, QC
from .pooling import CRITERION_POOLING, MEAN, TILES, check_pooling, tile_starts

#: FLIP's linear sRGB -> XYZ (its exact rational entries) and XYZ -> linear sRGB (D65)
RGB_TO_XYZ = ((10135552 / 24577794, 8788810 / 24577794, 4435075 / 24577794),
              (2613072 / 12288897, 8788810 / 12288897, 887015 / 12288897),
              (1425312 / 73733382, 8788810 / 73733382, 70074185 / 73733382))
XYZ_TO_RGB = ((3.241003275, -1.537398934, -0.498615861),
              (-0.969224334, 1.875930071, 0.041554224),
              (0.055639423, -0.204011202, 1.057148933))
ILLUMINANT = (0.950428545, 1.0, 1.088900371)
INV_ILLUMINANT = (1.052156925, 1.0, 0.918357670)
#: contrast-sensitivity Gaussians a * sqrt(pi / b) * exp(-pi^2 x^2 / b) per channel (Y, Cx,
#: Cz), x in degrees; Cz is the sum of two (FLIP's GaussianConstants a1, b1, a2, b2)
CSF_Y, CSF_CX, CSF_CZ = (1.0, 0.0047), (1.0, 0.0053), ((34.1, 0.04), (13.5, 0.025))
CSF_WIDEST_B = 0.04
GW = 0.082                           # feature detector width (degrees); its exponent is 1/2
#: tile length of the banded products (pixels of output per gathered window)
TILE = 16
#: pixels (blocks x height x width) per chunk: bounds the working memory (~200 bytes a
#: pixel), and keeps the intermediate tensors small enough to be recycled by the allocator
#: (at 2^17 and more, fresh pages cost a fifth of the time: ~5000 page faults per call)
CHUNK_PIXELS = 1 << 16
#: on a GPU: a 1024x1024 frame's blocks in one chunk (FLIP's intermediates: ~0.5 KB a pixel)
GPU_CHUNK_PIXELS = 1 << 21

_f32 = np.float32


def check_ppd(ppd: float) -> float:
    """FLIP's pixels per degree as a positive finite float, else ValueError."""
    try:
        p = float(ppd)
    except (TypeError, ValueError):
        raise ValueError(f"ppd must be a positive number, got {ppd!r}") from None
    if not math.isfinite(p) or p <= 0:
        raise ValueError(f"ppd must be a positive finite number, got {ppd!r}")
    return p


def spatial_radius(ppd: float) -> int:
    """FLIP's colour-filter radius in pixels (float32 arithmetic, as in FLIP)."""
    pi_sq = _f32(math.pi) * _f32(math.pi)
    return int(math.ceil(_f32(3.0) * np.sqrt(_f32(CSF_WIDEST_B) / (_f32(2.0) * pi_sq)) * _f32(ppd)))


def feature_sigma(ppd: float) -> float:
    """FLIP's edge/point detector's standard deviation in pixels (0.5 x 0.082 degrees)."""
    return float(_f32(0.5) * _f32(GW) * _f32(ppd))


@lru_cache(maxsize=16)
def colour_kernels(ppd: float) -> np.ndarray:
    """[4, 2r + 1] float64: FLIP's separated colour filters, rows Y, Cx, Cz1, Cz2.

    Y and Cx are normalised to sum 1; Cz1 and Cz2 are the square roots of the two Cz
    Gaussians, scaled together so that the 2D filter Cz1 x Cz1 + Cz2 x Cz2 sums to 1."""
    r = spatial_radius(ppd)
    x = (np.arange(-r, r + 1) / ppd) ** 2

    def gauss(a: float, b: float, root: bool = False) -> np.ndarray:
        amp = math.sqrt(a * math.sqrt(math.pi / b)) if root else a * math.sqrt(math.pi / b)
        return amp * np.exp(-math.pi ** 2 * x / b)

    y, cx = gauss(*CSF_Y), gauss(*CSF_CX)
    z1, z2 = (gauss(a, b, root=True) for a, b in CSF_CZ)
    norm = math.sqrt(z1.sum() ** 2 + z2.sum() ** 2)
    return np.stack([y / y.sum(), cx / cx.sum(), z1 / norm, z2 / norm])


@lru_cache(maxsize=16)
def feature_kernels(ppd: float) -> np.ndarray:
    """[3, 2r + 1] float64: FLIP's feature filters, rows Gaussian (sum 1), first and second
    derivative (positive lobes sum to 1, negative ones to -1)."""
    sd = feature_sigma(ppd)
    r = int(math.ceil(float(_f32(3.0) * _f32(sd))))
    x = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-x * x / (2 * sd * sd))
    dg, ddg = -x * g, (x * x / (sd * sd) - 1.0) * g

    def lobes(k: np.ndarray) -> np.ndarray:
        return np.where(k > 0, k / k[k > 0].sum(), k / -k[k < 0].sum())
    return np.stack([g / g.sum(), lobes(dg), lobes(ddg)])


def _tiling(n: int) -> tuple[int, int]:
    """(tile length, number of tiles) for an axis of n pixels: tiles of about TILE."""
    count = -(-n // TILE)
    return -(-n // count), count


def trimmed(kernel: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """`kernel` without the outer taps below `tol` x its peak: they cannot change a float32
    sum (FLIP's Y and Cx filters span 21 taps at 67 ppd, but their outer four and three on
    each side weigh under 1e-9 of the centre one), and a narrower filter costs less."""
    small = np.abs(kernel) < tol * np.abs(kernel).max()
    cut = 0
    while cut < len(kernel) // 2 and small[cut] and small[-1 - cut]:
        cut += 1
    return kernel[cut:len(kernel) - cut]


@lru_cache(maxsize=16)
def filter_bank(ppd: float) -> dict[str, np.ndarray]:
    """FLIP's 1D filters at `ppd` by name: the colour filters Y, Cx (trimmed), Cz1, Cz2 and
    the feature filters g, dg, ddg."""
    ck, fk = colour_kernels(ppd), feature_kernels(ppd)
    return {"Y": trimmed(ck[0]), "Cx": trimmed(ck[1]), "Cz1": ck[2], "Cz2": ck[3],
            "g": fk[0], "dg": fk[1], "ddg": fk[2]}


def _radius(ppd: float, names: tuple[str, ...]) -> int:
    return max(len(filter_bank(ppd)[k]) for k in names) // 2


@lru_cache(maxsize=128)
def _band(ppd: float, names: tuple[str, ...], t: int, transpose: bool = False) -> torch.Tensor:
    """[t + 2r, k t] float32 (or its contiguous transpose): column (i, j) applies filter
    names[i] to the window of output j; r is the widest filter's radius."""
    bank, r = filter_bank(ppd), _radius(ppd, names)
    m = np.zeros((t + 2 * r, len(names), t))
    for i, name in enumerate(names):
        taps = bank[name]
        pad = r - len(taps) // 2
        for j in range(t):
            m[pad + j:pad + j + len(taps), i, j] = taps
    m = m.reshape(t + 2 * r, len(names) * t)
    return torch.from_numpy(np.ascontiguousarray(m.T if transpose else m).astype(np.float32))


@lru_cache(maxsize=256)
def _band_on(ppd: float, names: tuple[str, ...], t: int, transpose: bool, device: torch.device) -> torch.Tensor:
    """`_band` on `device`, copied there once (the GPU loop calls FLIP every pass)."""
    return _band(ppd, names, t, transpose).to(device)


@lru_cache(maxsize=64)
def _row_windows(n: int, r: int, device: torch.device = torch.device("cpu")) -> tuple[torch.Tensor, int, int]:
    """Clamped indices of every tile's window along an axis of n pixels: (idx, t, count)."""
    t, count = _tiling(n)
    idx = (np.arange(count)[:, None] * t + np.arange(-r, t + r)[None]).clip(0, n - 1)
    return torch.from_numpy(idx.reshape(-1).astype(np.int64)).to(device), t, count


def _along_w(x: torch.Tensor, ppd: float, groups: list[tuple[str, ...]]) -> list[torch.Tensor]:
    """[B, H, W] -> per group of filter names, [B, H, nT, k, T]: each filter along W,
    borders clamped; the groups share one gathered window matrix, one GEMM each."""
    b, h, w = x.shape
    r = max(_radius(ppd, g) for g in groups)
    t, count = _tiling(w)
    # clamped borders: the edge pixel repeated (a concatenation is ~8x faster than a gather)
    xp = torch.cat([x[..., :1].expand(b, h, r), x, x[..., -1:].expand(b, h, r + count * t - w)], dim=2)
    win = xp.unfold(2, t + 2 * r, t).reshape(b * h * count, t + 2 * r)
    out = []
    for names in groups:
        q = _radius(ppd, names)
        sub = win if q == r else win[:, r - q:win.shape[1] - (r - q)]
        out.append((sub @ _band_on(ppd, names, t, False, x.device)).view(b, h, count, len(names), t))
    return out


def _along_h(x: torch.Tensor, ppd: float, names: tuple[str, ...], out: torch.Tensor | None = None,
             add: bool = False) -> torch.Tensor:
    """[B, H, *rest] -> [B, nT, k, T, *rest]: each filter along H, borders clamped; written
    into (or, with `add`, added to) `out`, a contiguous tensor of that many elements."""
    b, h, rest = x.shape[0], x.shape[1], x.shape[2:]
    idx, t, count = _row_windows(h, _radius(ppd, names), x.device)
    win = x.index_select(1, idx).view(b * count, len(idx) // count, -1)
    band = _band_on(ppd, names, t, True, x.device).expand(b * count, len(names) * t, len(idx) // count)
    if out is None:
        res = torch.bmm(band, win)
    elif add:
        res = out.view(b * count, len(names) * t, -1).baddbmm_(band, win)
    else:
        res = torch.bmm(band, win, out=out.view(b * count, len(names) * t, -1))
    return res.view(b, count, len(names), t, *rest)


_LAB_EPS = (6.0 / 29.0) ** 3
_LAB_SLOPE = 1.0 / (3.0 * (6.0 / 29.0) ** 2)


def _lab_f(t: torch.Tensor) -> torch.Tensor:
    """CIELab's f, in place: the cube root above (6/29)^3 and FLIP's line below, written
    without a branch as cbrt(m) + slope (t - m), m = max(t, (6/29)^3), and the cube root
    as exp(log(m) / 3) (torch's pow with a float exponent is ~3x slower)."""
    m = t.clamp_min(_LAB_EPS)
    return t.sub_(m).mul_(_LAB_SLOPE).add_(m.log_().mul_(1.0 / 3.0).exp_())


@lru_cache(maxsize=8)
def _affine(device: torch.device = torch.device("cpu")) -> tuple[torch.Tensor, ...]:
    """float32 (to_opp, opp_bias, from_opp, rgb_bias, to_xyz): linear RGB -> Y, Cx, Cz;
    filtered Y, Cx, Cz -> linear RGB; linear RGB -> XYZ / white ([3, 3] and [3, 1])."""
    to_xyz = np.diag(INV_ILLUMINANT) @ np.asarray(RGB_TO_XYZ)
    opp = np.array([[0.0, 116.0, 0.0], [500.0, -500.0, 0.0], [0.0, 200.0, -200.0]])
    # Y, Cx, Cz -> X, Y, Z (times the white) -> RGB: affine, as is RGB -> Y, Cx, Cz
    back = np.array([[1 / 116, 1 / 500, 0.0], [1 / 116, 0.0, 0.0], [1 / 116, 0.0, -1 / 200]])
    from_opp = np.asarray(XYZ_TO_RGB) @ np.diag(ILLUMINANT) @ back
    rgb_bias = np.asarray(XYZ_TO_RGB) @ np.diag(ILLUMINANT) @ np.full(3, 16 / 116)
    mats = (opp @ to_xyz, np.array([-16.0, 0.0, 0.0]), from_opp, rgb_bias, to_xyz)
    return tuple(torch.tensor(m.reshape(3, -1), dtype=torch.float32, device=device) for m in mats)


@lru_cache(maxsize=1)
def _cmax() -> float:
    """FLIP's largest colour error: Hunt-adjusted HyAB between green and blue, ^ 0.7."""
    to_xyz = _affine()[4]
    f = _lab_f(to_xyz @ torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]))   # green, blue
    lum, a, b = 116.0 * f[1] - 16.0, 500.0 * (f[0] - f[1]), 200.0 * (f[1] - f[2])
    ha, hb = 0.01 * lum * a, 0.01 * lum * b
    dist = (lum[0] - lum[1]).abs() + torch.sqrt((ha[0] - ha[1]) ** 2 + (hb[0] - hb[1]) ** 2)
    return float(dist ** QC)


def _flip_maps_linear(lin: torch.Tensor, ppd: float) -> torch.Tensor:
    """[3, 2N, H, W] linear RGB planes in [0, 1] (references, then tests) -> [N, H, W]
    FLIP maps."""
    _, n2, h, w = lin.shape
    n = n2 // 2
    to_opp, opp_bias, from_opp, rgb_bias, to_xyz = _affine(lin.device)
    y, cx, cz = torch.addmm(opp_bias, to_opp, lin.view(3, -1)).view(3, n2, h, w)

    # along W, one GEMM per group of filters; along H, one per group of outputs sharing a
    # filter. Features run on Y itself: FLIP's (Y + 16) / 116 is affine and its feature
    # filters are normalised (derivatives sum to 0), so they are Y's features / 116.
    slopes, smooth, ycsf = _along_w(y, ppd, [("dg", "ddg"), ("g",), ("Y",)])
    d1 = _along_h(slopes, ppd, ("g",))[:, :, 0]                  # [.., nTw, 2, Tw]: dx, ddx
    d2 = _along_h(smooth[:, :, :, 0], ppd, ("dg", "ddg"))        # [.., 2, Th, ..]: dy, ddy
    (cxw,) = _along_w(cx, ppd, [("Cx",)])
    z1, z2 = _along_w(cz, ppd, [("Cz1",), ("Cz2",)])
    # the filtered Y, Cx, Cz planes, each [2N, nTh, Th, nTw, Tw]
    th, nth = _tiling(h)
    tw, ntw = _tiling(w)
    opp = torch.empty(3, n2, nth, th, ntw, tw, device=lin.device)
    _along_h(ycsf[:, :, :, 0], ppd, ("Y",), out=opp[0])
    _along_h(cxw[:, :, :, 0], ppd, ("Cx",), out=opp[1])
    _along_h(z1[:, :, :, 0], ppd, ("Cz1",), out=opp[2])
    _along_h(z2[:, :, :, 0], ppd, ("Cz2",), out=opp[2], add=True)
    shape = opp.shape

    # colour: back to linear RGB, clamped; XYZ / white; Lab; Hunt; HyAB ^ 0.7; compressed
    rgb = torch.addmm(rgb_bias, from_opp, opp.view(3, -1)).clamp_(0.0, 1.0)
    f = _lab_f(to_xyz @ rgb).view(shape)
    lum = f[1].mul(116.0).sub_(16.0)
    ha = f[0].sub_(f[1]).mul_(500.0 * 0.01).mul_(lum)                  # 0.01 L a
    hb = f[1].sub_(f[2]).mul_(200.0 * 0.01).mul_(lum)                  # 0.01 L b
    da, db = ha[:n] - ha[n:], hb[:n] - hb[n:]
    colour = da.mul_(da).addcmul_(db, db).sqrt_().add_((lum[:n] - lum[n:]).abs_())
    colour = colour.log_().mul_(QC).exp_()
    cmax = _cmax()
    knee = PC * cmax
    above = (colour - knee).clamp_min_(0.0).mul_((1.0 - PT) / (cmax - knee))
    colour = colour.clamp_max_(knee).mul_(PT / knee).add_(above)       # FLIP's two pieces

    # features: edge and point magnitudes of A and B, their larger difference
    dx, ddx, dy, ddy = d1[..., 0, :], d1[..., 1, :], d2[:, :, 0], d2[:, :, 1]
    edge = (dx * dx).addcmul_(dy, dy).sqrt_()
    point = (ddx * ddx).addcmul_(ddy, ddy).sqrt_()
    feature = torch.maximum((edge[:n] - edge[n:]).abs_(), (point[:n] - point[n:]).abs_())
    feature = feature.mul_(1.0 / (116.0 * math.sqrt(2.0))).sqrt_()       # ^ 0.5 (FLIP's qf)

    # colour ^ (1 - feature) as exp((1 - feature) log colour); 0 ^ 0 is 1, as in powf
    err = colour.log_().mul_(feature.neg_().add_(1.0)).exp_().nan_to_num_(nan=1.0)
    b, nth, th, ntw, tw = err.shape
    return err.view(b, nth * th, ntw * tw)[:, :h, :w]


def _planes(a: torch.Tensor, b: torch.Tensor, exposure: float | None) -> torch.Tensor:
    """[3, 2N, H, W] float32 linear planes in [0, 1] of a then b: the display rule's
    clipped linear values (`exposure` a number), or sRGB values decoded (None)."""
    x = torch.cat([a.to(torch.float32).permute(3, 0, 1, 2), b.to(torch.float32).permute(3, 0, 1, 2)], dim=1)
    if exposure is None:        # FLIP clamps its inputs to [0, 1]; NaN is not an sRGB value
        return srgb_decode(x.nan_to_num_(nan=0.0).clamp_(0.0, 1.0)).clamp_(0.0, 1.0)
    return clipped_linear(x, exposure)


def _check_pair(a: torch.Tensor | np.ndarray, b: torch.Tensor | np.ndarray,
                what: str) -> tuple[torch.Tensor, torch.Tensor]:
    ta, tb = torch.as_tensor(a), torch.as_tensor(b)
    if ta.shape != tb.shape or ta.ndim != 4 or ta.shape[-1] != 3:
        raise ValueError(f"{what} must be two [N, H, W, 3] arrays of one shape, got "
                         f"{tuple(ta.shape)} and {tuple(tb.shape)}")
    if not (ta.is_floating_point() and tb.is_floating_point()):
        raise ValueError(f"{what} must be floating point, got {ta.dtype} and {tb.dtype}")
    return ta, tb


def _chunks(n: int, h: int, w: int, device: torch.device = torch.device("cpu")) -> list[tuple[int, int]]:
    """Blocks per call: cache-sized on the CPU; on a GPU as many as fit a large launch (a
    chunk is ~100 small kernels, so fewer chunks is what makes FLIP cheap there)."""
    step = max(1, (CHUNK_PIXELS if device.type == "cpu" else GPU_CHUNK_PIXELS) // max(1, h * w))
    return [(i, min(n, i + step)) for i in range(0, n, step)]


def ldr_flip(reference: torch.Tensor | np.ndarray, test: torch.Tensor | np.ndarray,
             ppd: float = DEFAULT_PPD) -> torch.Tensor:
    """float32 [N, H, W]: the raw LDR-FLIP map of each pair of sRGB images in [0, 1],
    [N, H, W, 3] each: what `flip_evaluator.evaluate(ref, test, "LDR", applyMagma=False)`
    returns for each pair alone (values outside [0, 1] are clamped, as FLIP clamps them)."""
    ref, tst = _check_pair(reference, test, "reference and test images")
    p = check_ppd(ppd)
    n, h, w = ref.shape[:3]
    out = torch.zeros((n, h, w))
    if h * w == 0:
        return out
    with torch.inference_mode():
        for i, j in _chunks(n, h, w):
            out[i:j] = _flip_maps_linear(_planes(ref[i:j], tst[i:j], None), p)
    return out


def flip_halves(even: torch.Tensor | np.ndarray, odd: torch.Tensor | np.ndarray,
                exposure: float = 0.0, ppd: float = DEFAULT_PPD, pooling: str = CRITERION_POOLING) -> np.ndarray:
    """float64 [N]: per block, the LDR-FLIP map between display(even) and display(odd),
    linear RGB half buffers [N, h, w, 3], pooled as the observer pools (`noisefeat.pooling`:
    the largest 16x16 tile mean, or the block mean); non-finite values follow the display
    rule.

    The display images are never encoded: FLIP decodes its sRGB input back to linear
    first, so the clipped linear values are what it computes on (to float32 rounding).
    A block whose two display images are identical gets exactly 0, as from FLIP."""
    return flip_halves_tensor(even, odd, exposure, ppd, pooling).cpu().numpy()


def flip_halves_tensor(even: torch.Tensor | np.ndarray, odd: torch.Tensor | np.ndarray,
                       exposure: float = 0.0, ppd: float = DEFAULT_PPD,
                       pooling: str = CRITERION_POOLING) -> torch.Tensor:
    """`flip_halves` where the half buffers live: float64 [N] on their device.

    Why: the live loop keeps its accumulators on the renderer's device (a GPU with
    ``cuda_ad_rgb``), so FLIP runs there and only the N scores ever reach the host."""
    a, b = _check_pair(even, odd, "half buffers")
    p = check_ppd(ppd)
    check_pooling(pooling)
    out = torch.zeros(a.shape[0], dtype=torch.float64, device=a.device)
    with torch.inference_mode():
        for i, keep, maps in _maps_by_chunk(a, b, exposure, p):
            out[i + keep] = _pool(maps, pooling)
    return out


def flip_maps_tensor(even: torch.Tensor | np.ndarray, odd: torch.Tensor | np.ndarray,
                     exposure: float = 0.0, ppd: float = DEFAULT_PPD) -> torch.Tensor:
    """The LDR-FLIP maps between the display images of half buffers [N, h, w, 3], float32
    [N, h, w] on their device (0 where the two display images are identical): for pooling
    parts of a window apart (a block's tiles, each judged with its neighbours as context)."""
    a, b = _check_pair(even, odd, "half buffers")
    p = check_ppd(ppd)
    out = torch.zeros(a.shape[:3], dtype=torch.float32, device=a.device)
    with torch.inference_mode():
        for i, keep, maps in _maps_by_chunk(a, b, exposure, p):
            out[i + keep] = maps.to(torch.float32)
    return out


def _maps_by_chunk(a: torch.Tensor, b: torch.Tensor, exposure: float,
                   ppd: float) -> Iterator[tuple[int, torch.Tensor, torch.Tensor]]:
    """(first row, rows kept, their FLIP maps) per chunk of pairs [N, h, w, 3]: pairs whose
    display images are identical are left out (their FLIP is 0)."""
    n, h, w = a.shape[:3]
    if h * w == 0 or n == 0:
        return
    for i, j in _chunks(n, h, w, a.device):
        lin = _planes(a[i:j], b[i:j], exposure)
        m = j - i
        differ = (lin[:, :m] != lin[:, m:]).reshape(3, m, -1).any(dim=2).any(dim=0)
        keep = torch.nonzero(differ).flatten()          # identical display images score 0
        if keep.numel() == 0:
            continue
        if keep.numel() < m:
            lin = lin.index_select(1, torch.cat([keep, keep + m]))
        yield i, keep, _flip_maps_linear(lin, ppd)


def pool_tiles(maps: torch.Tensor, windows: Sequence[tuple[int, int, int, int]],
               pooling: str = CRITERION_POOLING) -> torch.Tensor:
    """FLIP maps [N, h, w] of whole blocks pooled over each of their tiles' (x, y, w, h)
    `windows` (`noisefeat.pooling.tile_windows`), as the observer pools, float64 [N, T] on
    their device: the tiles keep their block as FLIP's context. The live criterion and the
    calibration on stacks both judge a tile by this one function."""
    check_pooling(pooling)
    n, bh, bw = maps.shape
    _, _, tw, th = windows[0]
    grid = [(x, y, tw, th) for y in range(0, bh, th) for x in range(0, bw, tw)]
    if bh % th == 0 and bw % tw == 0 and list(map(tuple, windows)) == grid:    # tiles cut the block: one call
        tiles = maps.reshape(n, bh // th, th, bw // tw, tw).transpose(2, 3).reshape(-1, th, tw)
        return _pool(tiles, pooling).reshape(n, len(grid))
    return torch.stack([_pool(maps[:, y:y + h, x:x + w], pooling) for x, y, w, h in windows], dim=1)


def _pool(maps: torch.Tensor, pooling: str) -> torch.Tensor:
    """`noisefeat.pooling.pool_maps` of float32 maps [N, h, w], in float64 on the maps'
    device: a reshape where the tiles cut the block evenly, else a summed-area table with
    the last tile row and column flush with the edge (`noisefeat.pooling.tile_starts`)."""
    n, h, w = maps.shape
    if pooling == MEAN:
        return maps.sum(dim=(1, 2), dtype=torch.float64) / (h * w)
    th, tw = min(TILES[pooling], h), min(TILES[pooling], w)
    if h % th == 0 and w % tw == 0:
        sums = maps.reshape(n, h // th, th, w // tw, tw).sum(dim=(2, 4), dtype=torch.float64)
        return sums.amax(dim=(1, 2)) / (th * tw)
    sat = torch.zeros((n, h + 1, w + 1), dtype=torch.float64, device=maps.device)
    sat[:, 1:, 1:] = maps.double().cumsum(1).cumsum(2)
    y0 = torch.as_tensor(tile_starts(h, TILES[pooling]), device=maps.device)
    x0 = torch.as_tensor(tile_starts(w, TILES[pooling]), device=maps.device)
    y1, x1 = y0 + th, x0 + tw
    s = sat[:, y1][:, :, x1] - sat[:, y0][:, :, x1] - sat[:, y1][:, :, x0] + sat[:, y0][:, :, x0]
    return (s / (th * tw)).reshape(n, -1).amax(dim=1)
