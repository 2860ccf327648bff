"""Forged decision state in a checkpoint whose digest was recomputed: each unit's evidence
(the history criterion's sums) zeroed resumed with units stopping at their next decision
(converged 39 % -> 69 %), sums of 1e300 or every next decision at the latest the format
allows ran every unit to max spp. The half buffers the file holds give each unit's noise
now; a state that disagrees with them is refused in one line, before any pass is added."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from learning.data.npz import read_npz
from renderer.live.adaptive import adaptive_render
from renderer.live.checkpoint import CHECKPOINT
from renderer.live.passloop import PassLoop
from tests.renderer.test_checkpoint_forged_ranges import _forged
from tests.support.errors import assert_one_line_error, run
from tests.support.forgery import FORGERIES, killed_at

pytestmark = pytest.mark.slow

#: flip at tile grain (it decides from each tile's history), decisions skipped (defaults)
SETTINGS = {"resolution": 64, "block": 32, "tile": 16, "step": 8, "min_spp": 8, "max_spp": 256, "tau": 0.05,
            "seed": 3}
ARGS = ("--scene", "cornell", "--resolution", "64", "--block", "32", "--tile", "16", "--step", "8", "--min-spp", "8",
        "--max-spp", "256", "--tau", "0.05", "--seed", "3", "--checkpoint-every", "0")


@pytest.fixture(scope="module")
def unfinished(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The checkpoint of a render killed at its 12th decision (units hold evidence, some
    were judged in the last round, others skip decisions)."""
    out = tmp_path_factory.mktemp("ckpt") / "out"
    with pytest.MonkeyPatch.context() as m:
        m.setattr(PassLoop, "judge", killed_at(12))
        with pytest.raises(RuntimeError, match="simulated kill"):
            adaptive_render("cornell", out, progress=False, checkpoint_every=0.0, **SETTINGS)
    state = read_npz(out / CHECKPOINT, kind="checkpoint")
    assert not bool(state["done"]) and (state["evidence"][:, 1] > 0).sum() > 8
    return out


@pytest.mark.parametrize("case", FORGERIES)
def test_forged_decision_state_is_refused(case: str, unfinished: Path, tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    out = _forged(unfinished, tmp_path / "out", FORGERIES[case])
    rc, err = run(capsys, "render", *ARGS, "--out", str(out), "--resume")
    assert_one_line_error(rc, err, str(out / CHECKPOINT), "inconsistent checkpoint")
    assert not (out / "report.json").exists()


def test_the_unforged_checkpoint_resumes_to_the_uninterrupted_render(unfinished: Path, tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    out = _forged(unfinished, tmp_path / "out", lambda arrays: None)
    rc, err = run(capsys, "render", *ARGS, "--out", str(out), "--resume")
    assert rc == 0, err
    whole = tmp_path / "whole"
    assert run(capsys, "render", *ARGS, "--out", str(whole))[0] == 0
    assert (out / "report.json").exists()
    from learning.data.exr import read_exr
    np.testing.assert_array_equal(read_exr(out / "final.exr"), read_exr(whole / "final.exr"))
