"""Hardening, fourth round (issue 42): the cases a hostile user or a broken disk found, one
test each (each failed on the code before it)."""
from __future__ import annotations

import os

import numpy as np
import pytest

from learning.models.bundle import load_model
from renderer.criteria import BlockView, FlipCriterion

GREY = np.full((1, 64, 64, 3), 0.5, np.float32)
#: (even, odd) pairs whose halves disagree completely: noisy, however flat their mean
DISAGREE = {
    "NaN against grey": (np.full_like(GREY, np.nan), GREY),
    "1e38 against 0": (np.full_like(GREY, 1e38), np.zeros_like(GREY)),
    "+3.4e38 against -3.4e38": (np.full_like(GREY, 3.4e38), np.full_like(GREY, -3.4e38)),
    "-Inf against grey": (np.full_like(GREY, -np.inf), GREY),
    "black against white": (np.zeros_like(GREY), np.ones_like(GREY)),
}


@pytest.fixture(scope="module")
def halves_model():
    model = load_model()                      # the bundled model reads the half buffers
    assert model.needs_halves
    return model


@pytest.mark.parametrize("case", sorted(DISAGREE))
def test_disagreeing_halves_are_noisy_on_the_served_route(halves_model, case: str) -> None:
    """The halves route (the server's `assess_halves`) answers -1 for halves that disagree
    completely; control: two equal grey halves are flat, +1."""
    even, odd = DISAGREE[case]
    verdict, _, _ = halves_model.assess_halves(even, odd)
    assert verdict.tolist() == [-1], case
    assert halves_model.assess_halves(GREY, GREY.copy())[0].tolist() == [1]


@pytest.mark.parametrize("case", sorted(DISAGREE))
def test_disagreeing_halves_are_noisy_in_the_local_criteria(case: str) -> None:
    """The live loop's criteria follow the same rule: a flat mean over halves that disagree
    is not flat. Control: equal halves under the same mean are."""
    even, odd = DISAGREE[case]
    crit = FlipCriterion(0.05, tau=0.02)
    mean = GREY[0].astype(np.float64)        # what a mean of the halves may look like: flat
    view = BlockView(mean=mean, spp=2, halves=(even[0], odd[0]), half_spp=(1, 1))
    assert crit.decide([0], [view]).verdict.tolist() == [-1], case
    same = BlockView(mean=mean, spp=2, halves=(GREY[0], GREY[0].copy()), half_spp=(1, 1))
    assert crit.decide([0], [same]).verdict.tolist() == [1]


# --- forged checkpoints: validated by meaning, not only by shape ----------------------------

FORGERIES = {
    "sums x 1e300": lambda a: a.update(acc_sum=a["acc_sum"] * 1e300),
    "sums negated": lambda a: a.update(acc_sum=-a["acc_sum"]),
    "a weight above its samples": lambda a: a["acc_weight"].__setitem__((0, 0, 0, 0), a["acc_weight"].max() + 1),
    "a weight short in a block that dropped nothing": lambda a: a["acc_weight"].__setitem__((0, 0, 0, 0), 0),
    "a ratio of +Inf": lambda a: a["budget_ratio"].__setitem__(np.flatnonzero(a["budget_ratio_asked"])[0], np.inf),
    "a budget cost off the samples": lambda a: a["budget_cost"].__setitem__(1, a["budget_cost"][1] + 16),
}


@pytest.fixture(scope="module")
def budget_checkpoint(tmp_path_factory):
    """A finished budget render's folder (its checkpoint kept) and its report."""
    from renderer.adaptive import adaptive_render
    from renderer.criteria import VarianceCriterion

    out = tmp_path_factory.mktemp("forge") / "ok"
    opts = {"resolution": 32, "grid": (4, 4), "step": 4, "min_spp": 4, "max_spp": 24, "progress": False,
            "checkpoint_every": 0.0, "spp_budget": 12}
    report = adaptive_render("cornell", out, VarianceCriterion(0.05), **opts)
    return out, opts, report


@pytest.mark.parametrize("forgery", sorted(FORGERIES))
def test_a_forged_checkpoint_with_a_fresh_digest_is_refused(tmp_path, budget_checkpoint, forgery: str) -> None:
    """Each forgery keeps every shape and type and recomputes the digest (what a forger
    does); resuming from it is refused in one line naming the file. Control: the checkpoint
    as written resumes."""
    import shutil

    from learning.data.npz import read_npz, savez_bytes
    from renderer.adaptive import adaptive_render
    from renderer.checkpoint import CHECKPOINT
    from renderer.criteria import VarianceCriterion

    src, opts, report = budget_checkpoint
    out = tmp_path / "run"
    shutil.copytree(src, out)
    assert adaptive_render("cornell", out, VarianceCriterion(0.05), resume=True, **opts)["passes"] == report["passes"]
    arrays = read_npz(out / CHECKPOINT)
    arrays.pop("sha256")
    FORGERIES[forgery](arrays)
    (out / CHECKPOINT).write_bytes(savez_bytes(arrays, with_digest=True))
    with pytest.raises(ValueError) as err:
        adaptive_render("cornell", out, VarianceCriterion(0.05), resume=True, **opts)
    assert str(out / CHECKPOINT) in str(err.value) and "\n" not in str(err.value), forgery


@pytest.mark.parametrize("kind", ["/dev/zero", "FIFO"])
def test_a_checkpoint_that_is_a_device_or_a_fifo_is_refused_at_once(tmp_path, kind: str) -> None:
    """`--resume` with checkpoint.npz linked to /dev/zero (it grew to 23.5 GB) or a FIFO (it
    waited for ever): one line naming the file, before anything is read."""
    from renderer.adaptive import adaptive_render
    from renderer.checkpoint import CHECKPOINT
    from renderer.criteria import VarianceCriterion

    out = tmp_path / "run"
    out.mkdir()
    if kind == "FIFO":
        os.mkfifo(out / CHECKPOINT)
    else:
        os.symlink("/dev/zero", out / CHECKPOINT)
    with pytest.raises(ValueError) as err:
        adaptive_render("cornell", out, VarianceCriterion(0.05), resume=True, resolution=32, grid=(4, 4),
                        step=4, max_spp=8, progress=False)
    assert str(out / CHECKPOINT) in str(err.value) and "not a regular file" in str(err.value)
