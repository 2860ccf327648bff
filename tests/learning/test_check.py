"""check_dataset: every defect is found, with a message that says which."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from learning.data.check import ERROR, WARNING, check_dataset, check_stack
from learning.data.exr import read_exr, write_exr
from learning.data.synthetic import make_synthetic_stack

SPP = [4, 8, 16, 32]
THRESHOLDS = [8, 16, 32, None] * 4


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("good")
    make_synthetic_stack(root / "s", size=32, spp=SPP, thresholds=THRESHOLDS)
    return root / "s"


@pytest.fixture
def stack(good, tmp_path) -> Path:
    d = tmp_path / "data" / "s"
    shutil.copytree(good, d)
    return d


def _edit_meta(d: Path, **changes):
    meta = json.loads((d / "meta.json").read_text())
    meta.update(changes)
    (d / "meta.json").write_text(json.dumps(meta))


def _messages(root, severity=None):
    return [p.message for p in check_dataset(root) if severity in (None, p.severity)]


def _one(root, text, severity=ERROR):
    found = [p for p in check_dataset(root) if text in p.message]
    assert found, f"no problem mentioning {text!r} in {check_dataset(root)}"
    assert found[0].severity == severity
    return found[0]


def test_good_dataset_has_no_problem(stack):
    assert check_dataset(stack.parent) == []
    assert check_stack(stack, deep=False) == []


def test_missing_level_file(stack):
    (stack / "levels" / "000008.exr").unlink()
    p = _one(stack.parent, "missing level file levels/000008.exr (level 8 spp)")
    assert p.path == stack / "levels" / "000008.exr"


def test_shape_mismatch(stack):
    write_exr(stack / "levels" / "000016.exr", np.zeros((16, 32, 3), np.float32))
    write_exr(stack / "quick.exr", np.zeros((32, 16, 3), np.float32))
    msgs = _messages(stack.parent)
    assert any("shape mismatch: level 16 spp is 32x16, meta.json width x height is 32x32" in m
               for m in msgs)
    assert any("shape mismatch: quick image is 16x32" in m for m in msgs)
    _edit_meta(stack, width=64)  # now every image disagrees with meta (and block too)
    msgs = _messages(stack.parent)
    assert sum("shape mismatch" in m for m in msgs) == len(SPP) + 2
    assert any("block size" in m for m in msgs)


def test_non_increasing_spp(stack):
    _edit_meta(stack, spp=[4, 16, 8, 32])
    _one(stack.parent, "spp is not strictly increasing: spp[1] = 16 >= spp[2] = 8")


def test_block_size_not_matching_grid(stack):
    _edit_meta(stack, block=[16, 16])
    _one(stack.parent, "block size [16, 16] does not match grid [4, 4] for a 32x32 image "
                       "(expected [8, 8])")
    _edit_meta(stack, block=[8, 8], grid=[5, 4])
    msgs = _messages(stack.parent)
    assert any("block size does not match grid" in m and "5x4 grid" in m for m in msgs)


def test_nan_in_reference_is_an_error_and_in_a_level_a_warning(stack):
    ref = read_exr(stack / "reference.exr")
    ref[0, 0, 0] = np.nan
    ref[1, 2, 1] = np.inf
    write_exr(stack / "reference.exr", ref)
    lev = read_exr(stack / "levels" / "000004.exr")
    lev[5, 5, 2] = np.nan
    write_exr(stack / "levels" / "000004.exr", lev)
    _one(stack.parent, "reference has 2 NaN/Inf value(s)")
    _one(stack.parent, "level 4 spp has 1 NaN/Inf value(s)", WARNING)


def test_truncated_exr(stack):
    p = stack / "levels" / "000032.exr"
    p.write_bytes(p.read_bytes()[:200])
    found = _one(stack.parent, "unreadable EXR (level 32 spp)")
    assert "000032.exr" in found.message and found.path == p
    assert check_stack(stack, deep=False) == []  # shallow mode does not read images


def test_thresholds_length(stack):
    _edit_meta(stack, thresholds=THRESHOLDS[:15])
    _one(stack.parent, "thresholds has 15 entries, the 4x4 grid has 16 blocks")


def test_threshold_not_int_or_not_in_spp(stack):
    _edit_meta(stack, thresholds=[8.5, "16"] + THRESHOLDS[2:])
    _one(stack.parent, "block 0: 8.5")
    _one(stack.parent, "block 1: '16'")
    _edit_meta(stack, thresholds=[12] + THRESHOLDS[1:], labeler={"name": "flip", "tau": 0.02})
    _one(stack.parent, "threshold of block 0 (12 spp) is not in the spp list")
    _edit_meta(stack, labeler={"name": "human", "source": "LISIC"})
    _one(stack.parent, "threshold of block 0 (12 spp) is not in the spp list", WARNING)


def test_missing_meta_json_incomplete_build(stack):
    meta = json.loads((stack / "meta.json").read_text())
    (stack / "meta.json").unlink()
    (stack / "meta.partial.json").write_text(json.dumps(meta))
    _one(stack.parent, "missing meta.json (incomplete build")
    (stack / "meta.partial.json").unlink()
    _one(stack.parent, "missing meta.json (not a complete stack)")


def test_broken_meta_json(stack):
    (stack / "meta.json").write_text("{ broken")
    _one(stack.parent, "meta.json is not valid JSON")


def test_every_problem_is_reported_at_once(stack, good, tmp_path):
    (stack / "levels" / "000008.exr").unlink()
    (stack / "quick.exr").unlink()
    p = stack / "levels" / "000016.exr"
    p.write_bytes(p.read_bytes()[:100])
    _edit_meta(stack, thresholds=THRESHOLDS[:3], block=[4, 4])
    write_exr(stack / "levels" / "000064.exr", np.zeros((32, 32, 3), np.float32))
    shutil.copytree(good, tmp_path / "data" / "other")
    (tmp_path / "data" / "other" / "reference.exr").unlink()
    problems = check_dataset(tmp_path / "data")
    text = "\n".join(str(x) for x in problems)
    for part in ("missing level file levels/000008.exr", "missing file quick.exr",
                 "unreadable EXR (level 16 spp)", "thresholds has 3 entries",
                 "block size [4, 4]", "level file not listed in meta.json spp",
                 "other/reference.exr: missing file reference.exr"):
        assert part in text, part
    assert len(problems) == 7


def test_empty_or_missing_root(tmp_path):
    assert [p.message for p in check_dataset(tmp_path)] == [
        "no stack found (no meta.json anywhere below)"]
    assert "does not exist" in check_dataset(tmp_path / "nope")[0].message


def test_quick_none_is_accepted(stack):
    (stack / "quick.exr").unlink()
    _edit_meta(stack, quick="none")
    assert check_dataset(stack.parent) == []
