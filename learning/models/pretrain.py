"""Pre-training the feature base's 12 conv layers as a denoiser on our stacks.

The paper took its conv layers from an earlier trained network; ours learn from noisy
level -> reference pairs (L* channel): the twelve layers together are one denoiser, the
loss is MSE(O_12, reference) and the intermediate outputs are its partial stages. (Pulling
every O_l to the reference was tried first: on low-noise blocks it drives all layers
towards the identity, and the loss rose under Adam.)
The wavelet layer is fixed. Training runs in the frequency domain (the base's circular
convolutions are products there; Parseval turns the MSE into a spectral sum), so a few
hundred Adam steps take seconds on the CPU. Only training scenes may be used: features
of held-out scenes must not have seen them.
"""
from __future__ import annotations

import logging
import time
from collections import Counter
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from noisefeat import FeatureBase
from noisefeat.base import column_weights
from noisefeat.display import lightness

from ..data.stack import Stack

log = logging.getLogger(__name__)


def denoising_pairs(stacks: list[Stack], per_stack: int = 96, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """(noisy L*, reference L*) blocks [N, h, w], levels drawn uniformly; one block size."""
    sizes = Counter(tuple(s.block) for s in stacks)
    size = sizes.most_common(1)[0][0]
    rng = np.random.default_rng(seed)
    noisy, clean = [], []
    for st in stacks:
        if tuple(st.block) != size:
            log.info("%s: block %s differs from %s; skipped for pre-training", st.scene, st.block, size)
            continue
        ref = lightness(torch.from_numpy(st.split(st.reference())))
        levels = rng.integers(0, st.n_levels, size=per_stack)
        for k in np.unique(levels):
            blocks = lightness(torch.from_numpy(st.blocks(int(k))))
            ids = rng.integers(0, st.n_blocks, size=int((levels == k).sum()))
            noisy.append(blocks[ids])
            clean.append(ref[ids])
    if not noisy:
        raise ValueError("no stack to pre-train on")
    return torch.cat(noisy), torch.cat(clean)


def spectral_loss(base: FeatureBase, noisy_f: torch.Tensor, clean_f: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """mean over blocks of MSE(O_12, reference), by Parseval on rfft2 spectra."""
    resp = base.transfer(h, w)[-1]                                     # [h, wr], with grad
    diff = resp[None] * noisy_f - clean_f                              # [n, h, wr]
    return ((diff.real ** 2 + diff.imag ** 2) * column_weights(w, diff.shape[-1])).sum(
        dim=(-2, -1)).mean() / float(h * w) ** 2


def pretrain_base(stacks: list[Stack], base: FeatureBase | None = None, steps: int = 300,
                  lr: float = 0.01, per_stack: int = 96, seed: int = 0,
                  progress: bool = True) -> tuple[FeatureBase, dict[str, Any]]:
    """Train the conv kernels of `base` (default: the smoothing initialisation) in place."""
    torch.manual_seed(seed)
    base = base or FeatureBase(weights="smoothing")
    t0 = time.perf_counter()
    noisy, clean = denoising_pairs(stacks, per_stack, seed)
    h, w = noisy.shape[-2:]
    with torch.no_grad():
        noisy_f, clean_f = torch.fft.rfft2(noisy), torch.fft.rfft2(clean)
        loss0 = float(spectral_loss(base, noisy_f, clean_f, h, w))
        identity = float(((noisy - clean) ** 2).mean())
    opt = torch.optim.Adam(base.convs.parameters(), lr=lr)
    losses = []
    for _ in tqdm(range(steps), desc="pre-training conv base", disable=not progress, leave=False):
        opt.zero_grad()
        loss = spectral_loss(base, noisy_f, clean_f, h, w)
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    base._transfer_cache.clear()
    report = {"pairs": int(len(noisy)), "block": [int(h), int(w)], "steps": steps, "lr": lr,
              "mse_noisy": identity, "mse_smoothing_init": loss0, "mse_trained": min(losses),
              "scenes": [s.scene for s in stacks], "seconds": time.perf_counter() - t0}
    log.info("conv base: MSE(O_12, reference) %.3f (smoothing init) -> %.3f; noisy input %.3f",
             loss0, losses[-1], identity)
    return base, report
