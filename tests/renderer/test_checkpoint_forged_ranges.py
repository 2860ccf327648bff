"""Forged checkpoints whose digest was recomputed: huge counters ended the
resumed render in an OverflowError "(a bug)", a timer of 1e308 was reported as wall_s with
exit 0, and sums scaled by 1e30 resumed with every block converged. Each is refused in one
line naming the file, before any pass is added."""
from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest

from learning.data.npz import DIGEST_KEY, read_npz, savez_bytes
from renderer.live.checkpoint import CHECKPOINT
from tests.support.errors import assert_one_line_error, run

pytestmark = pytest.mark.slow

ARGS = ("--scene", "cornell", "--resolution", "32", "--block", "16", "--criterion", "flip", "--max-spp", "256",
        "--step", "8", "--checkpoint-every", "0")


@pytest.fixture(scope="module")
def unfinished(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An out folder holding the checkpoint of a render stopped by its time limit."""
    from service import cli

    out = tmp_path_factory.mktemp("ckpt") / "out"
    assert cli.main(["render", *ARGS, "--out", str(out), "--time-limit", "0.000001"]) == 0
    state = read_npz(out / CHECKPOINT, kind="checkpoint")
    assert not bool(state["done"]) and int(state["pass_index"]) < 32
    return out


def _forged(src: Path, dst: Path, change: Callable[[dict[str, np.ndarray]], None]) -> Path:
    shutil.copytree(src, dst)
    arrays = {k: v for k, v in read_npz(dst / CHECKPOINT, kind="checkpoint").items() if k != DIGEST_KEY}
    change(arrays)
    (dst / CHECKPOINT).write_bytes(savez_bytes(arrays, with_digest=True))
    return dst


def _set(key: str, value: Any) -> Callable[[dict[str, np.ndarray]], None]:
    def change(arrays: dict[str, np.ndarray]) -> None:
        arrays[key] = np.full_like(arrays[key], value)
    return change


def _scale_sums(arrays: dict[str, np.ndarray]) -> None:
    arrays["acc_sum"] = arrays["acc_sum"] * 1e30


def _more_samples_weighed_than_decided(arrays: dict[str, np.ndarray]) -> None:
    arrays["evidence"] = np.tile([[1.0, 1e6]], (len(arrays["evidence"]), 1))


FORGERIES = {"huge counters": _set("counter_values", 2**62), "a timer of 1e308": _set("timer_values", 1e308),
             "sums x1e30": _scale_sums,
             # the decision history's evidence: what a history criterion decides from
             "negative evidence": _set("evidence", -1.0), "NaN evidence": _set("evidence", np.nan),
             "more samples weighed than decided": _more_samples_weighed_than_decided,
             # each unit's next decision: never before its last one
             "a next decision in the past": _set("next_spp", -1)}


@pytest.mark.parametrize("case", FORGERIES)
def test_a_forged_checkpoint_is_refused(case: str, unfinished: Path, tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    out = _forged(unfinished, tmp_path / "out", FORGERIES[case])
    before = (out / "report.json").read_bytes()          # the time-limited run's
    rc, err = run(capsys, "render", *ARGS, "--out", str(out), "--resume")
    assert_one_line_error(rc, err, str(out / CHECKPOINT))
    assert (out / "report.json").read_bytes() == before


def test_the_unforged_checkpoint_resumes(unfinished: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = _forged(unfinished, tmp_path / "out", lambda arrays: None)
    rc, err = run(capsys, "render", *ARGS, "--out", str(out), "--resume")
    assert rc == 0, err
