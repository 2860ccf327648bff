"""Arrays cached next to a stack are valid for the stack's content only."""
from __future__ import annotations

import dataclasses
import logging
import shutil

import numpy as np
import pytest

from learning import make_synthetic_stack
from learning.data.cache import CACHE_DIR, _atomic_savez, cached_array
from learning.data.exr import read_exr, write_exr
from learning.data.stack import read_stack


@pytest.fixture()
def stack(tmp_path):
    make_synthetic_stack(tmp_path / "s", size=32, spp=(4, 8, 16), label=False)
    return read_stack(tmp_path / "s")


def _cached(stack, calls):
    def compute():
        calls.append(1)
        return np.stack([stack.level(k).mean(axis=(0, 1)) for k in range(stack.n_levels)]).astype(np.float32)
    return cached_array(stack, "means", (stack.n_levels, 3), compute)


def test_a_changed_level_is_recomputed_and_a_copied_stack_is_not(stack, tmp_path):
    calls = []
    first = _cached(stack, calls)
    np.testing.assert_array_equal(_cached(stack, calls), first)
    assert len(calls) == 1                                           # read back
    level = stack.level_path(1)
    write_exr(level, read_exr(level) * 2)                             # same size, other content
    changed = _cached(stack, calls)
    assert len(calls) == 2 and not np.array_equal(changed, first)
    copy = read_stack(shutil.copytree(stack.path, tmp_path / "copy"))  # new mtimes, same bytes
    np.testing.assert_array_equal(_cached(copy, calls), changed)
    assert len(calls) == 2


def test_damaged_missing_or_unkeyed_caches_are_recomputed(stack, caplog):
    calls = []
    want = _cached(stack, calls)
    cache = stack.path / CACHE_DIR / "means.npz"
    cache.write_bytes(cache.read_bytes()[:100])                       # damaged
    with caplog.at_level(logging.WARNING):
        np.testing.assert_array_equal(_cached(stack, calls), want)
    assert len(calls) == 2 and "unreadable cache" in caplog.text
    _atomic_savez(cache, a=want * 0)                                  # a cache from before keys existed
    np.testing.assert_array_equal(_cached(stack, calls), want)
    assert len(calls) == 3


def test_a_missing_or_all_nan_level_is_refused_not_served_from_cache(stack):
    calls = []
    _cached(stack, calls)
    stack.level_path(2).unlink()
    with pytest.raises(FileNotFoundError, match="000016.exr"):
        _cached(stack, calls)
    write_exr(stack.level_path(2), np.full((32, 32, 3), np.nan, np.float32))
    with pytest.raises(ValueError, match="no finite pixel"):
        _cached(stack, calls)


def test_relabelling_keeps_the_caches_and_a_changed_plan_does_not(stack):
    from learning.data.stack_write import update_labels
    calls = []
    key = stack.content_key()
    _cached(stack, calls)
    relabelled = update_labels(stack, [16] * stack.n_blocks, {"name": "human"})
    assert relabelled.content_key() == key                            # labels are not an input
    _cached(relabelled, calls)
    assert len(calls) == 1
    other_plan = dataclasses.replace(relabelled, reference_spp=2 * relabelled.reference_spp)
    assert other_plan.content_key() != key                            # the plan is an input
