"""Sub-image tables: every (scene, level, block) of a dataset as one row.

The model input of the paper is features(quick) - features(level) per block; the raw SVM
uses the flattened L* block. Both are computed once per stack and feature base, and
cached next to the stack (`.cache/features-<basehash>.npz`, written atomically, valid for
the stack's content key only: `cached_array`), since a dataset is read by every train and
evaluate run.
"""
from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from tqdm import tqdm

from noisefeat import FeatureBase, default_base, extract_features
from noisefeat.display import lightness

from ..data.cache import cached_array
from ..data.dataset_dir import list_stacks
from ..data.relabel import observed
from ..data.stack import Stack, read_stack
from ..names import DEFAULT_TAU
from ..names import QUICK_MODES
from .halves import iter_stack_halves, stack_flat, stack_flip_errors, stack_halves_dots
from .noise_input import HALVES, RAW_COLUMNS, RAW_VERSION, compose, halves_raw, needs, noise_lightness
from .pictures import stack_pictures

log = logging.getLogger(__name__)


@dataclass
class SubImageTable:
    """Rows are sub-images; `groups` = one id per (scene, level): the paper's CV groups."""

    X: np.ndarray                      # [n, 26] features(quick) - features(level)
    y: np.ndarray                      # [n] int8, -1 noisy / +1 converged
    scene: np.ndarray                  # [n] scene name
    level: np.ndarray                  # [n] level index within its stack
    block: np.ndarray                  # [n] block id, row-major
    spp: np.ndarray                    # [n] samples per pixel of the row's level
    groups: np.ndarray                 # [n] int group id
    flat: np.ndarray                   # [n] bool: the sub-image's display image is flat (stop rule)
    stacks: dict[str, Stack] = field(default_factory=dict)
    #: [n] bool: the input exists at this level (False where the half buffers are not both
    #: filled yet: the first level of a `halves` table); None = every row. Rows that are not
    #: decidable never stop (unless flat) and are never trained on.
    decidable: np.ndarray | None = None
    #: [n] the criteria's dot term of a `halves` table's rows (`stack_halves_dots`): a row
    #: whose term exceeds its stack's tau never stops, as in the live loop; None: no guard
    dots: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.decidable is None:
            self.decidable = np.ones(len(self.y), bool)

    def __len__(self) -> int:
        return len(self.y)

    def subset(self, mask: np.ndarray) -> "SubImageTable":
        keep = set(np.unique(self.scene[mask]).tolist())
        return SubImageTable(self.X[mask], self.y[mask], self.scene[mask], self.level[mask],
                             self.block[mask], self.spp[mask], self.groups[mask], self.flat[mask],
                             {k: v for k, v in self.stacks.items() if k in keep}, self.decidable[mask],
                             None if self.dots is None else self.dots[mask])

    def trainable(self) -> "SubImageTable":
        """The rows a model may be fitted on (its input exists there)."""
        return self if self.decidable.all() else self.subset(self.decidable)

    def scene_mask(self, scenes: list[str]) -> np.ndarray:
        return np.isin(self.scene, list(scenes))

    def scenes(self) -> list[str]:
        return sorted(self.stacks)

    def relabelled(self, tau: float) -> "SubImageTable":
        """The same rows labelled by the observer at `tau` (`observed`: virtual-observer
        stacks relabelled from cached errors, human labels kept): the inputs do not change
        with the noise target, only which rows count as converged."""
        stacks = {name: observed(st, tau) for name, st in self.stacks.items()}
        y = self.y.copy()
        for name, st in stacks.items():
            rows = self.scene == name
            y[rows] = st.labels()[self.level[rows], self.block[rows]]
        return dataclasses.replace(self, y=y, stacks=stacks)


def feature_input(current: np.ndarray, quick: np.ndarray | None = None) -> np.ndarray:
    """The feature models' input from 26-feature rows: features(quick) - features(current).

    quick=None stands for a flat quick image (quick mode 'none'), whose features are all
    zero. Training (this table), `Model` and the render loop all build inputs here.
    """
    return -current if quick is None else quick - current


def raw_input(blocks: np.ndarray | torch.Tensor, exposure: float = 0.0) -> np.ndarray:
    """The raw SVM's input: L*/100 of linear RGB blocks [N, h, w, 3], flattened to [N, h*w]."""
    blocks = np.asarray(blocks)
    if blocks.ndim != 4 or blocks.shape[-1] != 3:
        raise ValueError(f"expected linear RGB blocks [N, h, w, 3], got shape {blocks.shape}")
    L = lightness(torch.as_tensor(blocks), exposure).numpy() / 100.0
    return L.reshape(len(L), blocks.shape[1] * blocks.shape[2]).astype(np.float32)


def stack_features(stack: Stack, base: FeatureBase | None = None, exposure: float = 0.0,
                   progress: bool = False, quick: str = "albedo") -> np.ndarray:
    """[K, n_blocks, D] model inputs of one stack, cached per feature base and quick mode.

    quick='halves': `learning.inputs.noise_input` on the stack's half buffers (first level: no
    odd half yet, see `stack_decidable`); 'albedo': features(the stack's quick image) - features(level); 'direct': the
    same with the stack's extra direct-lighting quick image; 'none': a flat quick image,
    whose features are all zero, so the input is -features(level).
    """
    if quick not in QUICK_MODES:
        raise ValueError(f"quick must be one of {QUICK_MODES}, got {quick!r}")
    base = base or default_base()
    if quick == "halves":
        return stack_halves_input(stack, base, exposure, progress)

    def compute() -> np.ndarray:
        quick_feats = None if quick == "none" else extract_features(
            stack.split(stack.quick(None if quick == "albedo" else quick)), base=base, exposure=exposure)
        rows = []
        for k in tqdm(range(stack.n_levels), desc=f"{stack.scene} features", disable=not progress,
                      leave=False):
            rows.append(feature_input(extract_features(stack.blocks(k), base=base, exposure=exposure),
                                      quick_feats))
        return np.stack(rows).astype(np.float32)
    return cached_array(stack, f"features-{base.hash}-e{exposure:g}-{quick}",
                        (stack.n_levels, stack.n_blocks, 26), compute)


def _per_level_halves(stack: Stack, name: str, width: int, fn: Callable[[np.ndarray, np.ndarray], np.ndarray],
                      progress: bool = False) -> np.ndarray:
    """[K, n_blocks, width] fn(even, odd) of every (level, block) (`iter_stack_halves`);
    zeros at the first level. Cached as `name`."""
    def compute() -> np.ndarray:
        out = np.zeros((stack.n_levels, stack.n_blocks, width), np.float32)
        for k, even, odd in iter_stack_halves(stack, progress):
            out[k] = fn(even, odd)
        return out
    return cached_array(stack, name, (stack.n_levels, stack.n_blocks, width), compute)


def stack_halves_raw(stack: Stack, base: FeatureBase | None = None, exposure: float = 0.0,
                     progress: bool = False) -> np.ndarray:
    """[K, n_blocks, 54] `noise_input.halves_raw` of every (level, block) (`_per_level_halves`)."""
    base = base or default_base()
    return _per_level_halves(stack, f"halves-v{RAW_VERSION}-{base.hash}-e{exposure:g}", RAW_COLUMNS,
                             lambda a, b: halves_raw(a, b, exposure, base), progress)


def stack_raw_halves(stack: Stack, exposure: float = 0.0) -> np.ndarray:
    """[K, n_blocks, bh*bw] the raw noise image (L*(A) - L*(B)) / 100 of every sub-image:
    the raw SVM's `halves` input (`_per_level_halves`)."""
    return _per_level_halves(stack, f"raw-halves-e{exposure:g}", stack.block[0] * stack.block[1],
                             lambda a, b: noise_lightness(a, b, exposure))


def stack_halves_input(stack: Stack, base: FeatureBase | None = None, exposure: float = 0.0,
                       progress: bool = False, composition: str = HALVES) -> np.ndarray:
    """[K, n_blocks, D] `halves` model inputs of a stack (`noise_input.compose` of the cached
    half-buffer features and FLIP values; first level: not decidable, see `stack_decidable`)."""
    feats, flip = needs(composition)
    k, b = stack.n_levels, stack.n_blocks
    raw = stack_halves_raw(stack, base, exposure, progress).reshape(k * b, -1) if feats else None
    e = stack_flip_errors(stack, exposure, progress=progress).reshape(-1) if flip else None
    return compose(raw, e, composition).reshape(k, b, -1)


def stack_decidable(stack: Stack, quick: str) -> np.ndarray:
    """bool [K, n_blocks]: where the model input exists (halves: from the second level on)."""
    ok = np.ones((stack.n_levels, stack.n_blocks), bool)
    if quick == "halves":
        ok[0] = False
    return ok


def stack_raw_blocks(stack: Stack, exposure: float = 0.0) -> np.ndarray:
    """[K, n_blocks, bh*bw] L*/100 of every sub-image: the raw SVM's input."""
    return np.stack([raw_input(stack.blocks(k), exposure) for k in range(stack.n_levels)])


def load_table(root: str | os.PathLike, *, raw: bool = False, base: FeatureBase | None = None,
               scenes: list[str] | None = None, progress: bool = True,
               quick: str = "albedo", composition: str = HALVES, image: bool = False,
               tau: float = DEFAULT_TAU) -> SubImageTable:
    """All labelled stacks under root as one table, labelled by the observer at `tau`
    (`learning.data.relabel.observed`: a stack of another observer is relabelled in
    memory, human labels are kept as they are): model inputs of `quick` (a `halves`
    table in `composition`); raw L* blocks instead of features if `raw` (with quick
    'halves': the raw noise image; any other quick: the block itself); with `image`, the
    pictures an image classifier reads, X [n, bh, bw, 3] (`learning.inputs.pictures`:
    quick 'none' the block, 'halves' its noise picture)."""
    if image and raw:
        raise ValueError("a table holds raw L* rows or pictures, not both")
    paths = list_stacks(root)
    if not paths:
        raise ValueError(f"{root}: no stacks found (no meta.json below it)")
    xs, ys, sc, lv, bl, sp, gr, fl, ok, dots, stacks = [], [], [], [], [], [], [], [], [], [], {}
    gid = 0
    for p in tqdm(paths, desc="stacks", disable=not progress, leave=False):
        st = read_stack(p)
        if scenes is not None and st.scene not in scenes:
            continue
        if st.thresholds is None:
            log.warning("%s: no labels (thresholds); skipped", p)
            continue
        if st.scene in stacks:
            raise ValueError(f"{p}: scene name {st.scene!r} appears twice in {root}")
        st.validate()            # every file, the reference included: damage named, never trained on
        st = observed(st, tau)
        stacks[st.scene] = st
        if image:
            x = stack_pictures(st, quick)
        elif raw:
            x = stack_raw_halves(st) if quick == "halves" else stack_raw_blocks(st)
        elif quick == "halves":
            x = stack_halves_input(st, base, composition=composition)
        else:
            x = stack_features(st, base, quick=quick)
        k, b = x.shape[:2]
        xs.append(x.reshape(k * b, *x.shape[2:]) if image else x.reshape(k * b, -1))
        ys.append(st.labels().reshape(-1))
        sc.append(np.full(k * b, st.scene, dtype=object))
        lv.append(np.repeat(np.arange(k), b))
        bl.append(np.tile(np.arange(b), k))
        sp.append(np.repeat(np.asarray(st.spp), b))
        gr.append(gid + np.repeat(np.arange(k), b))
        fl.append(stack_flat(st).reshape(-1))
        ok.append(stack_decidable(st, quick).reshape(-1))
        if quick == "halves":
            dots.append(stack_halves_dots(st).reshape(-1))
        gid += k
    if not stacks:
        raise ValueError(f"{root}: no labelled stack matched")
    if (raw or image) and len({x.shape[1:] for x in xs}) > 1:
        raise ValueError(f"{'raw-pixel' if raw else 'image'} models need one block size across the dataset")
    return SubImageTable(np.concatenate(xs), np.concatenate(ys).astype(np.int8), np.concatenate(sc),
                         np.concatenate(lv), np.concatenate(bl), np.concatenate(sp),
                         np.concatenate(gr), np.concatenate(fl), stacks, np.concatenate(ok),
                         np.concatenate(dots) if dots else None)


def rgb_blocks(table: SubImageTable, halves: bool = False) -> np.ndarray:
    """Linear RGB sub-images [n, h, w, 3] of every row of `table`, in row order: the block,
    or with `halves` its noise picture (`stack_pictures`)."""
    st0 = next(iter(table.stacks.values()))
    out = np.empty((len(table), *st0.block, 3), np.float32)
    for scene, st in table.stacks.items():
        rows = np.flatnonzero(table.scene == scene)
        out[rows] = stack_pictures(st, "halves" if halves else "none")[table.level[rows], table.block[rows]]
    return out
