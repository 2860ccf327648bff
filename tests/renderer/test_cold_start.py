"""What a short render need not pay (a user times the whole command)."""
from __future__ import annotations

import numpy as np

from renderer.live.adaptive import adaptive_render
from renderer.live.checkpoint import CHECKPOINT
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


def test_the_spp_map_is_drawn_without_matplotlib() -> None:
    """The spp map every render writes costs no matplotlib import (0.5 s of every command),
    and it is a picture of the samples: viridis, log2 from min to max spp (the
    block at min spp dark purple, the one at max spp yellow), a red outline round a block
    that ran to max spp."""
    import io
    import subprocess
    import sys

    from PIL import Image

    code = ("import sys, numpy as np\n"
            "from renderer.live.outputs import spp_map_png\n"
            "spp = np.array([[16] * 32 + [1024] * 32] * 64, float)\n"
            "png = spp_map_png(spp, [[0, 0, 32, 64], [32, 0, 32, 64]], [16, 1024], [True, False], 16, 1024)\n"
            "sys.stdout.buffer.write(png)\n"
            "assert 'matplotlib' not in sys.modules, sorted(m for m in sys.modules if 'matplotlib' in m)[:3]\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=120)
    assert out.returncode == 0, out.stderr.decode()[-400:]
    img = np.asarray(Image.open(io.BytesIO(out.stdout)).convert("RGB")).astype(int)
    assert img.shape[0] >= 400 and img.std() > 10
    from renderer.live.outputs import MAP_SIZE, MARGIN
    scale = MAP_SIZE // 64
    low = img[MARGIN + 10 * scale, MARGIN + 5 * scale]            # inside the 16-spp block
    high = img[MARGIN + 10 * scale, MARGIN + 60 * scale]          # inside the 1024-spp block
    assert low[2] > low[1] and low[0] > low[1]                    # viridis' dark purple
    assert high[0] > 200 and high[1] > 200 and high[2] < 80       # viridis' yellow
    edge = img[MARGIN + 32 * scale, MARGIN + 64 * scale - 1]      # the 1024 block's right edge: ran to max
    assert edge[0] > 180 and edge[1] < 80


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
