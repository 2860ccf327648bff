"""Decisions per tile: each tile of a block has its own samples and stop; the flip
criterion judges a tile with its block's pixels as context; tile = block is the block loop
(the golden fixture, tests/renderer/test_device_loop.py, holds at tile = block)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from learning.data.exr import read_exr
from renderer.live.adaptive import adaptive_render
from renderer.live.block_windows import BlockWindows
from renderer.live.checkpoint import CHECKPOINT
from renderer.criteria import FlipCriterion, VarianceCriterion
from renderer.live.passloop import PassLoop, schedule


def _one_noisy_tile(tiling: BlockWindows | None, n_passes: int = 4) -> tuple[PassLoop, list[np.ndarray]]:
    """A 64x64 block of 16x16 tiles, all a quiet grey but tile 5 (loud noise): the loop at
    the tiling's grain, fed `n_passes` passes."""
    rng = np.random.default_rng(0)
    t = 1 if tiling is None else tiling.tiles_per_block
    shape = (16, 16) if tiling is not None else (64, 64)
    loop = PassLoop(FlipCriterion(0.05, tau=0.02), (1, t), shape, schedule(8, 64), 8, tiling=tiling)
    rows = []
    for _ in range(n_passes):
        frame = 0.4 + 0.002 * rng.standard_normal((64, 64, 3))
        frame[16:32, 16:32] += 0.3 * rng.standard_normal((16, 16, 3))        # tile 5: row 1, column 1
        ids = np.flatnonzero(loop.active)
        if not ids.size:
            break
        units = frame.reshape(4, 16, 4, 16, 3).transpose(0, 2, 1, 3, 4).reshape(16, 16, 16, 3) \
            if tiling is not None else frame[None]
        rows.append(loop.run_round(ids, [(units[ids], 8)]))
    return loop, rows


def test_clean_tiles_stop_while_the_noisy_one_samples_on() -> None:
    """The observer's grain: the clean tiles away from the noisy one stop at the first
    decision, the noisy tile keeps sampling. (Its edge neighbours see its noise spread by
    FLIP's filters, as the observer's own FLIP map of the frame does.) Control: with tile =
    block the block holds the noisy tile, so nothing stops."""
    tiling = BlockWindows(64, 64, block=64, tile=16)
    loop, rows = _one_noisy_tile(tiling)
    assert tiling.tiles_per_block == 16
    row, col = np.divmod(np.arange(16), 4)
    away = (np.abs(row - 1) > 1) | (np.abs(col - 1) > 1)          # not touching tile 5
    assert (rows[0] == -1).all()                                   # one pass: no estimate yet
    assert (rows[1][away] == 1).all() and rows[1][5] == -1 and loop.active[5]
    assert not loop.active[away].any() and loop.active.sum() <= 9
    assert loop.acc.spp_all()[5] > loop.acc.spp_all()[15] == loop.stop_spp[15]
    assert int(np.nanargmax(loop.ratios.value)) == 5
    block, _ = _one_noisy_tile(None)
    assert block.active.tolist() == [True]


def test_a_tile_is_judged_in_its_blocks_context() -> None:
    """A tile's FLIP comes from the map of its whole block: the same tile judged alone (its
    own 16x16 window, no neighbours) scores differently, so the context is really used."""
    tiling = BlockWindows(64, 64, block=64, tile=16)
    loop, _ = _one_noisy_tile(tiling, n_passes=2)
    from renderer.criteria import UnitBatch

    batch = UnitBatch.from_accumulator(loop.acc, [4, 5, 6], tiling=tiling)
    in_context = FlipCriterion(0.05, tau=0.02)._flip(batch, np.arange(3))
    alone = FlipCriterion(0.05, tau=0.02)._flip(UnitBatch.from_accumulator(loop.acc, [4, 5, 6]), np.arange(3))
    assert in_context[1] > 0.05 and alone[1] > 0.05                   # the noisy tile either way
    assert not np.allclose(in_context, alone)


def test_a_tiles_halves_are_read_once_and_the_same_either_way() -> None:
    """`UnitBatch.halves_of`: a few tiles' halves, read alone before their blocks are put
    together and cut from the assembled tiles after, are every unit's halves (`halves`)
    bit for bit, in any order; a frame of two blocks, so a tile's block row matters."""
    import torch

    from renderer.criteria import UnitBatch

    tiling = BlockWindows(128, 64, block=64, tile=16)
    rng = np.random.default_rng(3)
    loop = PassLoop(FlipCriterion(0.05, tau=0.02), (2, 16), (16, 16), schedule(8, 64), 8, tiling=tiling)
    for _ in range(3):
        loop.acc.add_batch(np.arange(32), 0.5 + 0.1 * rng.standard_normal((32, 16, 16, 3)), 8)
    ids, rows = [3, 17, 30, 5], np.array([2, 0, 3])
    whole = UnitBatch.from_accumulator(loop.acc, ids, tiling=tiling).halves
    before = UnitBatch.from_accumulator(loop.acc, ids, tiling=tiling)
    early = before.halves_of(rows)
    after = UnitBatch.from_accumulator(loop.acc, ids, tiling=tiling)
    after.block_halves(np.arange(4))                        # the blocks put together first
    late = after.halves_of(rows)
    assert after._halves is None                            # no unit's halves read again
    for j in (0, 1):
        assert torch.equal(early[j], whole[j][torch.from_numpy(rows)])
        assert torch.equal(late[j], whole[j][torch.from_numpy(rows)])


def test_tiles_fill_their_blocks() -> None:
    """Tiles cut every block alike, flush with the block's edge; put back together they are
    the block's window, overlaps included."""
    import torch

    for block, tile, per_block in ((64, 16, 16), (40, 16, 9), (32, 32, 1)):
        w = BlockWindows(100, 72, block=block, tile=tile)
        assert w.tiles_per_block == per_block and w.n_units == w.n_blocks * per_block
        frame = torch.arange(100 * 72, dtype=torch.float64).reshape(-1, 1)
        tiles = frame[w._unit_idx].reshape(w.n_blocks, per_block, w.tile_h, w.tile_w, 1)
        blocks = frame[w._win_idx].reshape(w.n_blocks, w.block_h, w.block_w, 1)
        assert torch.equal(w.assemble(tiles), blocks)
        last = torch.full((w.block_h, w.block_w), -1, dtype=torch.int64)    # where tiles overlap: the later one's
        for t, (dx, dy, tile_w, tile_h) in enumerate(w.tile_windows()):
            n = tile_h * tile_w
            last[dy:dy + tile_h, dx:dx + tile_w] = torch.arange(t * n, (t + 1) * n).reshape(tile_h, tile_w)
        assert torch.equal(w._block_from_tiles, last.flatten())
        x, y, tw, th = w.unit_window(w.n_units - 1)
        assert (x + tw, y + th) == (100, 72)


@pytest.mark.slow
def test_a_render_at_tile_grain_resumes_bit_for_bit(tmp_path) -> None:
    """Killed after its second checkpoint, a tile-grain render resumes to the uninterrupted
    image and report; a checkpoint of the block-grain format (version 3) is refused in one
    line."""
    from renderer.criteria import VarianceCriterion as Variance

    class Crashing(Variance):
        def _decide(self, ids, batch, tally):
            self.calls = getattr(self, "calls", 0) + 1
            if self.calls == 3:
                raise RuntimeError("simulated kill")
            return super()._decide(ids, batch, tally)

    kw = {"resolution": 64, "block": 32, "tile": 16, "step": 4, "min_spp": 8, "max_spp": 48, "progress": False,
          "checkpoint_every": 0.0, "grow": False}
    ref = adaptive_render("cornell", tmp_path / "a", VarianceCriterion(0.2), **kw)
    assert ref["tile"] == [16, 16] and len(ref["tiles"]) == 16 and ref["passes"] > 3
    spp = [t["spp"] for t in ref["tiles"]]
    assert len(set(spp)) > 1                                     # tiles stopped apart
    with pytest.raises(RuntimeError, match="simulated kill"):
        adaptive_render("cornell", tmp_path / "b", Crashing(0.2), **kw)
    resumed = adaptive_render("cornell", tmp_path / "b", VarianceCriterion(0.2), resume=True, **kw)
    timing = {"wall_s", "timing", "render_calls"}
    assert {k: v for k, v in resumed.items() if k not in timing} == {k: v for k, v in ref.items() if k not in timing}
    np.testing.assert_array_equal(read_exr(tmp_path / "b" / "final.exr"), read_exr(tmp_path / "a" / "final.exr"))
    on_disk = json.loads((tmp_path / "b" / "report.json").read_text())
    assert on_disk["tiles"] == ref["tiles"] and on_disk["blocks"] == ref["blocks"]
    # the blocks summarise their tiles: mean spp, done when every tile is
    for b in ref["blocks"]:
        own = [t for t in ref["tiles"] if t["block"] == b["id"]]
        assert b["spp"] == round(np.mean([t["spp"] for t in own])) and b["converged"] == all(t["converged"] for t in own)
    # an older checkpoint format: one line, no resume
    import numpy.lib.format  # noqa: F401  (np.load of the npz below)

    with np.load(tmp_path / "b" / CHECKPOINT, allow_pickle=False) as z:
        data = {k: z[k] for k in z.files}
    data["version"] = np.int64(3)
    np.savez(tmp_path / "b" / CHECKPOINT, **data)
    with pytest.raises(ValueError, match="checkpoint version 3, this noisestop reads version 6"):
        adaptive_render("cornell", tmp_path / "b", VarianceCriterion(0.2), resume=True, **kw)


def test_the_model_and_the_oracle_decide_whole_blocks_unless_told() -> None:
    """The learned model's unit is the paper's block: left unset, its tile is the block;
    given a smaller tile it gates flip's tile verdicts (`GatedCriterion`). The oracle's
    thresholds are per block: a smaller tile is refused in one line."""
    from renderer.criteria import GatedCriterion, ModelCriterion, make_criterion
    from renderer.spec import resolve

    spec = resolve({"criterion": "model"})
    assert spec.tile >= spec.block and "whole blocks" in spec.sources["tile"]
    assert resolve({}).tile == 16 and resolve({"criterion": "variance"}).tile == 16
    assert isinstance(make_criterion(resolve({"criterion": "model"}, frame=(256, 256))), ModelCriterion)
    gated = make_criterion(resolve({"criterion": "model", "tile": 16}, frame=(256, 256)))
    assert isinstance(gated, GatedCriterion) and gated.tiles.unit == "tile16"
    with pytest.raises(ValueError, match="the oracle criterion decides whole blocks"):
        resolve({"criterion": "oracle", "tile": 16}, thresholds_known=True, frame=(256, 256))


class _Gate:
    """A verdict model that answers every block the same (a server's shape: verdicts only)."""

    needs_quick = False

    def __init__(self, verdict: int) -> None:
        self.verdict, self.seen = verdict, []

    def score_blocks(self, blocks, quick=None, exposure=0.0, offset=None):
        self.seen.append(np.asarray(blocks).shape)
        return np.full(len(blocks), self.verdict), None


@pytest.mark.parametrize("gate", [1, -1])
def test_the_models_block_verdict_gates_the_tiles(gate: int) -> None:
    """A tile stops when flip calls it converged and the model calls its whole block
    converged: an open gate stops exactly the tiles flip alone stops, a closed one none,
    and the model is shown whole 64x64 blocks, never tiles."""
    from renderer.criteria import GatedCriterion, ModelCriterion

    tiling = BlockWindows(64, 64, block=64, tile=16)
    flip_only, _ = _one_noisy_tile(tiling, n_passes=2)
    model = _Gate(gate)
    crit = GatedCriterion(ModelCriterion(model, tau=0.02), FlipCriterion(0.05, tau=0.02))
    loop = PassLoop(crit, (1, 16), (16, 16), schedule(8, 64), 8, tiling=tiling)
    rng = np.random.default_rng(0)
    for _ in range(2):                                  # the same passes as _one_noisy_tile's
        frame = 0.4 + 0.002 * rng.standard_normal((64, 64, 3))
        frame[16:32, 16:32] += 0.3 * rng.standard_normal((16, 16, 3))
        units = frame.reshape(4, 16, 4, 16, 3).transpose(0, 2, 1, 3, 4).reshape(16, 16, 16, 3)
        ids = np.flatnonzero(loop.active)
        loop.run_round(ids, [(units[ids], 8)])
    assert model.seen and all(shape == (1, 64, 64, 3) for shape in model.seen)
    if gate > 0:
        assert loop.active.tolist() == flip_only.active.tolist() and loop.ledger.counters["gated_tiles"] == 0
    else:
        assert loop.active.all() and loop.ledger.counters["gated_tiles"] == (~flip_only.active).sum()
