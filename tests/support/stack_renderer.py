"""Test helper: the live render loop fed a stored stack's own passes instead of Mitsuba's."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

from learning.inputs.halves import recover_passes
from noisefeat import split_blocks
from renderer.live import adaptive, plan
from renderer.live.block_windows import BlockWindows
from renderer.live.ledger import Ledger
from renderer.live.wavefront import Traced


class StackRenderer:
    """Stand-in for BlockRenderer that serves a stack's recovered passes: the live loop
    then sees exactly the samples the simulation sees. Its calls go to `ledger`, as the
    renderer's do (one Mitsuba call and launch per pass traced)."""

    def __init__(self, stack, grid):
        self.stack, self.grid = stack, tuple(grid)
        self.passes = [split_blocks(p, self.grid) for _, _, _, p in recover_passes(stack)]
        self.step = int(stack.spp[0])
        self.height, self.width = stack.height, stack.width
        self.block_h, self.block_w = stack.block
        self.block_shape = tuple(stack.block)
        self.n_blocks = self.n_units = stack.n_blocks
        self.tiles_per_block, self.tile_shape = 1, self.block_shape     # block grain: a block is its tile
        self.tile_h, self.tile_w = self.block_shape
        self.calls = []
        self.ledger = Ledger()
        self.device = torch.device("cpu")

    geometry = BlockWindows.geometry        # the cut as a run records it, from the attributes above

    def close(self):
        """Nothing to restore (BlockRenderer puts Dr.Jit's kernel-history flag back)."""

    def cut_blocks(self, frame):
        return split_blocks(frame, self.grid)

    def count_kernels(self):
        """No kernels: nothing to count."""

    def _called(self, ids, spp):
        self.calls.append(list(ids))
        self.ledger.count("mitsuba_calls")
        self.ledger.count("kernel_launches")
        self.ledger.count("samples_traced", len(ids) * self.block_h * self.block_w * spp)

    def block_slices(self, b):
        r, c = divmod(b, self.grid[1])
        return slice(r * self.block_h, (r + 1) * self.block_h), slice(c * self.block_w, (c + 1) * self.block_w)

    def window(self, b):
        rows, cols = self.block_slices(b)
        return cols.start, rows.start, self.block_w, self.block_h

    unit_window = window

    def render_units(self, ids, spp, seed, pass_index=0):
        assert spp == self.step
        self._called(ids, spp)
        return np.stack([self.passes[pass_index][b] for b in ids])

    def render_passes(self, jobs, spp, seed):
        sizes = [spp] * len(jobs) if isinstance(spp, int) else list(spp)
        assert all(s == self.step for s in sizes)
        for p in sorted({p for _, p in jobs}):          # one entry per pass traced
            self._called([b for b, q in jobs if q == p], self.step)
        return np.stack([self.passes[p][b] for b, p in jobs])

    def submit_passes(self, jobs, spp, seed):
        images = self.render_passes(jobs, spp, seed)
        return Traced(lambda: images)

    def quick_image(self, spp=16, seed=0, kind="albedo"):
        return self.stack.quick(kind)


def stack_scene(stack):
    """Stand-in for the loaded scene of `stack`: one sensor whose film is the stack's frame
    (what the render spec is fitted to)."""
    film = SimpleNamespace(crop_size=lambda: (stack.width, stack.height))
    return SimpleNamespace(sensors=lambda: [SimpleNamespace(film=lambda: film)], integrator=lambda: None)


def live(monkeypatch, tmp_path, stack, crit, min_spp, name="live", grow=False):
    """adaptive_render over `stack`'s passes; returns (report, the renderer used). One pass
    per launch unless `grow` (then passes traced past a block's stop are in `calls` too)."""
    made = []

    def fake_renderer(scene, grid=None, block=None, tile=None, sensor=None, integrator=None):
        made.append(StackRenderer(stack, grid))
        return made[-1]

    monkeypatch.setattr(plan, "BlockRenderer", fake_renderer)
    monkeypatch.setattr("renderer.scenes.catalog.load_scene",
                        lambda scene, resolution, defines=None: stack_scene(stack))
    report = adaptive.adaptive_render(stack.scene, tmp_path / name, crit, resolution=stack.width,
                                      grid=tuple(stack.grid), tile=max(stack.block), step=int(stack.spp[0]),
                                      min_spp=min_spp,
                                      max_spp=int(stack.spp[-1]), progress=False, grow=grow)
    return report, made[0]
