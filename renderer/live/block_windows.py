"""Where a frame's blocks and tiles lie, in pixels: arithmetic only, the same for every engine.

Blocks are a grid that divides the frame (``grid=(rows, cols)``: stacks, references) or windows every
`block` pixels (the live render of any film), the last row and column flush with the frame's edge, so
every window the criterion sees is a full block of one sample count, the size the model and the flip
threshold were calibrated on (the final image takes each pixel from the covering window with the most
samples: `compose`). Each block is cut into tiles of `tile` pixels by the same rule: the loop's units
(unit u is tile u % T of block u // T; without a tile size a block is its one tile).
"""
from __future__ import annotations

import numpy as np
import torch

from noisefeat.blocks import compose
from noisefeat.pooling import tile_starts, tile_windows

__all__ = ["BlockWindows", "compose"]


class BlockWindows:
    """The blocks of a `width` x `height` frame, numbered row-major, block 0 top-left: windows
    of `block` pixels, else a `grid` (rows, columns); checked where they are given (the render
    spec: a block no larger than the frame, a grid that divides it)."""

    def __init__(self, width: int, height: int, grid: tuple[int, int] | None = None,
                 block: int | None = None, tile: int | None = None) -> None:
        self.width, self.height = width, height
        if block is not None:
            self.block_h = self.block_w = int(block)
            self._xs = tile_starts(self.width, int(block)).tolist()
            self._ys = tile_starts(self.height, int(block)).tolist()
        else:
            gh, gw = (int(g) for g in grid)  # type: ignore[union-attr]
            self.block_h, self.block_w = self.height // gh, self.width // gw
            self._xs = [c * self.block_w for c in range(gw)]
            self._ys = [r * self.block_h for r in range(gh)]
        self.grid = (len(self._ys), len(self._xs))
        # flat pixel indices of every window [n, bh * bw], to gather a pass's blocks at once
        ys = torch.tensor(self._ys)[:, None, None, None] + torch.arange(self.block_h)[None, None, :, None]
        xs = torch.tensor(self._xs)[None, :, None, None] + torch.arange(self.block_w)[None, None, None, :]
        self._win_idx = (ys * self.width + xs).reshape(self.n_blocks, -1)
        self._tiles = tile_windows(self.block_h, self.block_w,
                                   max(self.block_h, self.block_w) if tile is None else tile)
        self.tile_w, self.tile_h = self._tiles[0][2:]
        ox, oy = torch.tensor(self._tiles).T[:2, :, None, None]
        # each tile's pixels in its block [T, th * tw]
        inner = ((oy + torch.arange(self.tile_h)[:, None]) * self.block_w + ox + torch.arange(self.tile_w)).flatten(1)
        #: flat frame pixel indices of every unit (tile) window [n_units, th * tw]
        self._unit_idx = self._win_idx[:, inner.reshape(-1)].reshape(self.n_units, -1)
        #: where each pixel of a block window comes from: its last tile's (tile, row, column), the largest
        #: index (a reduction: an assignment through repeated indices leaves the winner unspecified)
        self._block_from_tiles = torch.full((self.block_h * self.block_w,), -1, dtype=torch.int64).scatter_reduce(
            0, inner.flatten(), torch.arange(inner.numel()), reduce="amax")

    def geometry(self) -> dict[str, tuple[int, int]]:
        """The cut in pixels, as a run records it: resolution (W, H), grid (rows, columns),
        block and tile (height, width)."""
        return {"resolution": (self.width, self.height), "grid": self.grid, "block": self.block_shape,
                "tile": self.tile_shape}

    @property
    def n_blocks(self) -> int:
        return self.grid[0] * self.grid[1]

    @property
    def tiles_per_block(self) -> int:
        return len(self._tiles)

    @property
    def n_units(self) -> int:
        """The loop's units: every block's tiles (the blocks themselves without tiles)."""
        return self.n_blocks * self.tiles_per_block

    @property
    def tile_shape(self) -> tuple[int, int]:
        """(tile height, tile width) in pixels: the units' shape."""
        return self.tile_h, self.tile_w

    def unit_window(self, unit: int) -> tuple[int, int, int, int]:
        """(x, y, width, height) of unit (tile) `unit` within the frame."""
        x, y = self.block_origin(int(unit) // self.tiles_per_block)
        dx, dy = self._tiles[int(unit) % self.tiles_per_block][:2]
        return x + dx, y + dy, self.tile_w, self.tile_h

    def tile_windows(self) -> list[tuple[int, int, int, int]]:
        """(x, y, width, height) of every tile inside its block."""
        return list(self._tiles)

    def assemble(self, tiles: torch.Tensor) -> torch.Tensor:
        """Block windows [k, bh, bw, C] from their tiles [k, T, th, tw, C] (where tiles
        overlap at a block's edge, the later tile's pixel)."""
        k, c = tiles.shape[0], tiles.shape[-1]
        src = self._block_from_tiles.to(tiles.device)
        return tiles.reshape(k, -1, c)[:, src].reshape(k, self.block_h, self.block_w, c)

    @property
    def block_shape(self) -> tuple[int, int]:
        """(block height, block width) in pixels."""
        return self.block_h, self.block_w

    @property
    def overlapping(self) -> bool:
        """Whether edge windows overlap their neighbours (block size not dividing the frame)."""
        return self._xs[-1] + self.block_w != len(self._xs) * self.block_w or \
            self._ys[-1] + self.block_h != len(self._ys) * self.block_h

    def block_origin(self, block_id: int) -> tuple[int, int]:
        """(x, y) of the block's top-left pixel within the frame."""
        if not isinstance(block_id, (int, np.integer)) or not 0 <= int(block_id) < self.n_blocks:
            raise ValueError(f"block id {block_id!r} out of range 0..{self.n_blocks - 1}")
        row, col = divmod(int(block_id), self.grid[1])
        return self._xs[col], self._ys[row]

    def window(self, block_id: int) -> tuple[int, int, int, int]:
        """(x, y, width, height) of the block within the frame."""
        x, y = self.block_origin(block_id)
        return x, y, self.block_w, self.block_h

    def cut_blocks(self, frame: np.ndarray) -> np.ndarray:
        """Every block's window of a host frame [H, W, C]: [n, bh, bw, C] (one gather)."""
        flat = np.asarray(frame).reshape(self.height * self.width, -1)
        return flat[self._win_idx.cpu().numpy()].reshape(self.n_blocks, self.block_h, self.block_w, -1)
