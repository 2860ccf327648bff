"""Issue 43: what a short render need not pay."""
from __future__ import annotations

import numpy as np

from renderer.adaptive import adaptive_render
from renderer.checkpoint import CHECKPOINT
from renderer.criteria import VarianceCriterion

TINY = {"resolution": 32, "grid": (2, 2), "step": 4, "min_spp": 4, "max_spp": 12, "progress": False}


def test_a_render_shorter_than_the_checkpoint_period_writes_no_checkpoint(tmp_path) -> None:
    """Within its first period a render writes no checkpoint (and removes a stale one an
    earlier run left); the same render checkpointed after every pass writes one, the same
    image either way."""
    from learning.data.exr import read_exr

    stale = tmp_path / "a" / CHECKPOINT
    stale.parent.mkdir()
    stale.write_bytes(b"left by an earlier run")
    short = adaptive_render("cornell", tmp_path / "a", VarianceCriterion(0.05), checkpoint_every=3600.0, **TINY)
    assert not stale.exists() and short["render_calls"]["checkpoints"] == 0
    every = adaptive_render("cornell", tmp_path / "b", VarianceCriterion(0.05), checkpoint_every=0.0, **TINY)
    assert (tmp_path / "b" / CHECKPOINT).exists() and every["render_calls"]["checkpoints"] == every["passes"]
    np.testing.assert_array_equal(read_exr(tmp_path / "a" / "final.exr"), read_exr(tmp_path / "b" / "final.exr"))


def test_warming_matplotlib_in_the_background_imports_it() -> None:
    """`warm_plotting` (started while a GPU render traces) imports matplotlib's Agg canvas
    in a daemon thread and ends; drawing the spp map afterwards needs no import."""
    import sys

    from renderer.outputs import warm_plotting

    thread = warm_plotting()
    assert thread.daemon
    thread.join(60)
    assert not thread.is_alive()
    assert "matplotlib.backends.backend_agg" in sys.modules and "matplotlib.figure" in sys.modules


def test_the_executable_exits_with_mains_status(tmp_path) -> None:
    """The `noisestop` executable (`service.cli.run`: main, then exit without the final
    collection) keeps main's exit status and output: 0 and the scene list for a command
    that works, 2 and one line for one that fails."""
    import subprocess
    import sys

    ok = subprocess.run([sys.executable, "-c", "from service.cli import run; run()", "scenes"],
                        capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0 and "cornell" in ok.stdout
    bad = subprocess.run([sys.executable, "-c", "from service.cli import run; run()", "render", "--scene",
                          str(tmp_path / "missing.xml"), "--out", str(tmp_path / "o")],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and bad.stderr.strip().splitlines()[-1].startswith("noisestop render: error:")
