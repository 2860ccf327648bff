"""`noisestop render` killed with SIGKILL at random passes, then `--resume`d, gives
the uninterrupted run's image and report, bit for bit (timings aside)."""
from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from learning.data.exr import read_exr
from learning.data.npz import read_npz

RENDER = ["render", "--scene", "cornell", "--resolution", "64", "--grid", "4", "4", "--step", "4",
          "--min-spp", "8", "--max-spp", "96", "--criterion", "variance", "--threshold", "0.2", "--json",
          "--checkpoint-every", "0"]     # a checkpoint after every pass: kills land at any of them


def _cli(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "service.cli", "-q", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _pass_index(path: Path) -> int:
    try:
        return int(read_npz(path)["pass_index"])
    except (ValueError, FileNotFoundError, KeyError):
        return -1


def _kill_at(out: Path, target: int, resume: bool, limit_s: float = 300) -> int | None:
    """Run (or resume) the render and SIGKILL it once its checkpoint reaches `target`
    passes; the pass it was killed after, or None if it finished first."""
    proc = _cli(*RENDER, "--out", str(out), *(["--resume"] if resume else []))
    deadline = time.monotonic() + limit_s
    try:
        while proc.poll() is None and time.monotonic() < deadline:
            reached = _pass_index(out / "checkpoint.npz")
            if reached >= target:
                os.kill(proc.pid, signal.SIGKILL)
                proc.wait(30)
                return _pass_index(out / "checkpoint.npz")
            time.sleep(0.005)
        assert proc.returncode == 0, proc.stderr.read() if proc.stderr else ""
        return None
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _without_timing(report: dict) -> dict:
    """What must be identical: everything but the process's costs (times, kernel compiles,
    checkpoints written)."""
    return {k: v for k, v in report.items() if k not in ("wall_s", "timing", "render_calls")}


@pytest.mark.slow
def test_kill_9_at_random_passes_then_resume_is_bit_identical(tmp_path):
    ref = _cli(*RENDER, "--out", str(tmp_path / "ref"))
    out, err = ref.communicate(timeout=300)
    assert ref.returncode == 0, err
    reference = json.loads(out)
    assert 0 < reference["blocks_converged"] < 16 and reference["passes"] > 8   # stops happen mid-run

    rng = random.Random(14)
    targets = sorted(rng.sample(range(1, reference["passes"] - 1), 3))
    killed = []
    for i, target in enumerate(targets):
        killed.append(_kill_at(tmp_path / "run", target, resume=i > 0))
    assert all(k is not None for k in killed) and killed == sorted(killed), killed
    final = _cli(*RENDER, "--out", str(tmp_path / "run"), "--resume")
    out, err = final.communicate(timeout=300)
    assert final.returncode == 0, err
    resumed = json.loads(out)
    assert _without_timing(resumed) == _without_timing(reference)
    np.testing.assert_array_equal(read_exr(tmp_path / "run" / "final.exr"), read_exr(tmp_path / "ref" / "final.exr"))
