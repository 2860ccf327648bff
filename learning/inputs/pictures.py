"""Pictures an image classifier reads: the block itself, or the displayed noise picture of
its half buffers (the transfer baselines' inputs, `learning.models.transfer`).

An ImageNet base reads a picture, not features, so its `halves` input is a picture too:
linear RGB whose display is 0.5 + display(A) - display(B) (clipped), content-free like the
SVMs' `halves` input. One home for training (tables), the comparison, bundles, the render
loop and the service, so all of them read the same pixels.
"""
from __future__ import annotations

import numpy as np
import torch

from noisefeat.display import display, srgb_decode

from ..data.stack import Stack
from .halves import check_halves, iter_stack_halves

#: linear value whose display is mid grey: the noise picture of a block with no noise
#: estimate yet (the first level, B still empty) and of a block without noise
GREY = float(srgb_decode(torch.tensor(0.5)))


def image_input(blocks: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """Linear RGB blocks [N, h, w, 3] as the classifier reads them at display `exposure`
    (it applies the display transform at exposure 0 itself): float32, scaled by 2^exposure."""
    blocks = np.asarray(blocks)
    if blocks.ndim != 4 or blocks.shape[-1] != 3:
        raise ValueError(f"expected linear RGB blocks [N, h, w, 3], got shape {list(blocks.shape)}")
    x = blocks.astype(np.float32, copy=exposure != 0.0)
    if exposure != 0.0:
        x *= np.float32(2.0 ** exposure)
    return x


def noise_picture(even: np.ndarray, odd: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """Linear RGB [N, h, w, 3] whose display is clip(0.5 + display(A) - display(B)):
    finite whatever A and B hold (non-finite pixels follow the display rule)."""
    even, odd = check_halves(even, odd)
    with torch.inference_mode():
        d = (0.5 + display(even, exposure) - display(odd, exposure)).clamp_(0.0, 1.0)
        return srgb_decode(d).numpy().astype(np.float32)


def stack_pictures(stack: Stack, quick: str) -> np.ndarray:
    """[K, n_blocks, bh, bw, 3] of every sub-image of a stack: the block (`quick` 'none') or
    its noise picture ('halves'; the first level, with no odd half yet, is flat grey)."""
    if quick not in ("none", "halves"):
        raise ValueError(f"an image classifier reads the block ('none') or its noise picture "
                         f"('halves'), not quick image {quick!r}")
    if quick == "none":
        return np.stack([stack.blocks(k).astype(np.float32) for k in range(stack.n_levels)])
    out = np.full((stack.n_levels, stack.n_blocks, *stack.block, 3), GREY, np.float32)
    for k, even, odd in iter_stack_halves(stack):
        out[k] = noise_picture(even, odd)
    return out
