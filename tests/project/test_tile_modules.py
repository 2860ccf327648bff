"""The `tile` setting is acted on in few modules during a render (the runtime trace of
`benchmarks.render_path`): a reader visits those to know what a tile does."""
from __future__ import annotations

from pathlib import Path

from benchmarks.render_path import acting_lines, render_path


def test_a_flip_render_acts_on_tile_in_at_most_six_modules() -> None:
    modules = render_path(resolution=32, max_spp=16)["tile_modules"]
    assert {"renderer/spec.py", "renderer/live/block_windows.py"} <= set(modules)   # resolved, then cut
    assert len(modules) <= 6, modules


def test_acting_lines_counts_only_functions_that_ran(tmp_path: Path) -> None:
    src = tmp_path / "m.py"
    src.write_text("def ran(s):\n    return s.tile\n\n\ndef idle(tile):\n    return tile\n\n\n"
                   "def keyed(d):\n    return d['tile'], d['other'], f(tile=1)\n")
    assert acting_lines(src, {1}) == [2]
    assert acting_lines(src, {5}) == [5, 6]
    assert acting_lines(src, {9}) == [10]
