"""LDR-FLIP maps of many image pairs at once: NVIDIA FLIP's computation, batched in torch.

What is computed is FLIP's LDR pipeline as `flip-evaluator` 1.7 runs it, on each block
alone, with the constants and filters of `noisefeat.flip_kernels` applied as banded
products (`noisefeat.flip_bands`):

* colour: linear RGB -> YCxCz, each channel low-passed by its contrast-sensitivity filter;
  back to linear RGB, clamped to [0, 1]; CIELab with the Hunt adjustment; HyAB distance ^
  0.7, compressed into [0, 1] with the knee at 0.4 cmax;
* features: the achromatic channel, (Y + 16) / 116, filtered by the Gaussian and its first
  and second derivatives; edge and point magnitudes; the feature difference
  sqrt(max(|d edge|, |d point|) / sqrt 2);
* error = colour ^ (1 - feature), per pixel.

Maps agree with flip-evaluator's to float32 rounding (tests/noisefeat/test_flip.py compares
the two on realistic and extreme blocks). `ldr_flip(reference, test)` takes sRGB images in
[0, 1] like `flip_evaluator.evaluate`; `flip_maps_tensor(even, odd)` takes linear half
buffers and follows the display rule (noisefeat.display: x 2^exposure, NaN/-Inf black,
+Inf white, clip to [0, 1]). Pooling the maps is `noisefeat.flip`'s.
"""
from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import torch

from .display import clipped_linear, srgb_decode
from .flip_bands import along_h, along_w, tiling
from .flip_kernels import check_ppd, cmax, colour_matrices, lab_f_inplace
from .perceptual import DEFAULT_PPD, PC, PT, QC

#: pixels (blocks x height x width) per chunk: bounds the working memory (~200 bytes a
#: pixel), and keeps the intermediate tensors small enough to be recycled by the allocator
#: (at 2^17 and more, fresh pages cost a fifth of the time: ~5000 page faults per call)
CHUNK_PIXELS = 1 << 16
#: on a GPU: a 1024x1024 frame's blocks in one chunk (FLIP's intermediates: ~0.5 KB a pixel)
GPU_CHUNK_PIXELS = 1 << 21


def _flip_maps_linear(lin: torch.Tensor, ppd: float) -> torch.Tensor:
    """[3, 2N, H, W] linear RGB planes in [0, 1] (references, then tests) -> [N, H, W]
    FLIP maps."""
    _, n2, h, w = lin.shape
    n = n2 // 2
    to_opp, opp_bias, from_opp, rgb_bias, to_xyz = colour_matrices(lin.device)
    y, cx, cz = torch.addmm(opp_bias, to_opp, lin.view(3, -1)).view(3, n2, h, w)

    # along W, one GEMM per group of filters; along H, one per group of outputs sharing a
    # filter. Features run on Y itself: FLIP's (Y + 16) / 116 is affine and its feature
    # filters are normalised (derivatives sum to 0), so they are Y's features / 116.
    slopes, smooth, ycsf = along_w(y, ppd, [("dg", "ddg"), ("g",), ("Y",)])
    d1 = along_h(slopes, ppd, ("g",))[:, :, 0]                  # [.., nTw, 2, Tw]: dx, ddx
    d2 = along_h(smooth[:, :, :, 0], ppd, ("dg", "ddg"))        # [.., 2, Th, ..]: dy, ddy
    (cxw,) = along_w(cx, ppd, [("Cx",)])
    z1, z2 = along_w(cz, ppd, [("Cz1",), ("Cz2",)])
    # the filtered Y, Cx, Cz planes, each [2N, nTh, Th, nTw, Tw]
    th, nth = tiling(h)
    tw, ntw = tiling(w)
    opp = torch.empty(3, n2, nth, th, ntw, tw, device=lin.device)
    along_h(ycsf[:, :, :, 0], ppd, ("Y",), out=opp[0])
    along_h(cxw[:, :, :, 0], ppd, ("Cx",), out=opp[1])
    along_h(z1[:, :, :, 0], ppd, ("Cz1",), out=opp[2])
    along_h(z2[:, :, :, 0], ppd, ("Cz2",), out=opp[2], add=True)
    shape = opp.shape

    # colour: back to linear RGB, clamped; XYZ / white; Lab; Hunt; HyAB ^ 0.7; compressed
    rgb = torch.addmm(rgb_bias, from_opp, opp.view(3, -1)).clamp_(0.0, 1.0)
    f = lab_f_inplace(to_xyz @ rgb).view(shape)
    lum = f[1].mul(116.0).sub_(16.0)
    ha = f[0].sub_(f[1]).mul_(500.0 * 0.01).mul_(lum)                  # 0.01 L a
    hb = f[1].sub_(f[2]).mul_(200.0 * 0.01).mul_(lum)                  # 0.01 L b
    da, db = ha[:n] - ha[n:], hb[:n] - hb[n:]
    colour = da.mul_(da).addcmul_(db, db).sqrt_().add_((lum[:n] - lum[n:]).abs_())
    colour = colour.log_().mul_(QC).exp_()
    top = cmax()
    knee = PC * top
    above = (colour - knee).clamp_min_(0.0).mul_((1.0 - PT) / (top - knee))
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


def check_pair(a: torch.Tensor | np.ndarray, b: torch.Tensor | np.ndarray,
               what: str) -> tuple[torch.Tensor, torch.Tensor]:
    """`a` and `b` as tensors, if they are two floating-point [N, H, W, 3] arrays of one
    shape; else a ValueError naming `what` (before any work is done on them)."""
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
    ref, tst = check_pair(reference, test, "reference and test images")
    p = check_ppd(ppd)
    n, h, w = ref.shape[:3]
    out = torch.zeros((n, h, w))
    if h * w == 0:
        return out
    with torch.inference_mode():
        for i, j in _chunks(n, h, w):
            out[i:j] = _flip_maps_linear(_planes(ref[i:j], tst[i:j], None), p)
    return out


def flip_maps_tensor(even: torch.Tensor | np.ndarray, odd: torch.Tensor | np.ndarray,
                     exposure: float = 0.0, ppd: float = DEFAULT_PPD) -> torch.Tensor:
    """The LDR-FLIP maps between the display images of half buffers [N, h, w, 3], float32
    [N, h, w] on their device (0 where the two display images are identical): for pooling
    parts of a window apart (a block's tiles, each judged with its neighbours as context)."""
    a, b = check_pair(even, odd, "half buffers")
    p = check_ppd(ppd)
    out = torch.zeros(a.shape[:3], dtype=torch.float32, device=a.device)
    with torch.inference_mode():
        for i, keep, maps in maps_by_chunk(a, b, exposure, p):
            out[i + keep] = maps.to(torch.float32)
    return out


def maps_by_chunk(a: torch.Tensor, b: torch.Tensor, exposure: float,
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

