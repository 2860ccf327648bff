"""`dataset relabel` refuses a stack whose reference `dataset check` calls an error: one NaN
or +Inf pixel in reference.exr used to move the labels silently (192 -> 336 spp, and a
neighbouring block 480 -> 624), exit 0, while `check` reported the very file."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from learning.data.check import ERROR, check_stack
from learning.data.exr import read_exr, write_exr
from tests.support import FIXTURE_DATASET
from tests.support.errors import assert_one_line_error, run


@pytest.fixture
def data(tmp_path) -> Path:
    """The fixture's checker stack alone, its caches left out, labelled at another tau than
    the one relabel is asked for (so relabel has work to do)."""
    root = tmp_path / "d"
    shutil.copytree(FIXTURE_DATASET / "checker", root / "checker", ignore=shutil.ignore_patterns(".cache"))
    return root


def _spoil_reference(stack: Path, value: float) -> None:
    ref = read_exr(stack / "reference.exr")
    ref[3, 3, 0] = value
    write_exr(stack / "reference.exr", ref)


@pytest.mark.parametrize("value", [np.nan, np.inf], ids=["NaN", "+Inf"])
def test_relabel_refuses_a_reference_that_check_calls_an_error(data, capsys, value) -> None:
    stack = data / "checker"
    _spoil_reference(stack, value)
    before = (stack / "meta.json").read_bytes()
    assert [p.severity for p in check_stack(stack)] == [ERROR]          # check's verdict: one error
    rc, err = run(capsys, "dataset", "relabel", str(data), "--tau", "0.03")
    assert_one_line_error(rc, err, "reference.exr", "1 NaN/Inf value", "not relabelled")
    assert (stack / "meta.json").read_bytes() == before                 # the labels are as they were


def test_relabel_still_relabels_a_clean_reference(data, capsys) -> None:
    """The control: the same stack, its reference intact, is relabelled at the new tau."""
    rc, err = run(capsys, "dataset", "relabel", str(data), "--tau", "0.03")
    assert rc == 0, err
    assert json.loads((data / "checker" / "meta.json").read_text())["labeler"]["tau"] == 0.03
