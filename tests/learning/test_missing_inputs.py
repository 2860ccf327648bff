"""The Python API's loaders raise ValueError for a path naming nothing: a
`noisefeat.errors.InputNotFound`, which is a FileNotFoundError too, naming the path."""
from __future__ import annotations

import pytest

import learning
from noisefeat.errors import InputNotFound


@pytest.mark.parametrize("load", [learning.load_model, learning.read_stack])
def test_a_missing_path_is_a_value_error_naming_it(load, tmp_path) -> None:
    gone = tmp_path / "nothing-here"
    for kind in (ValueError, FileNotFoundError, InputNotFound):
        with pytest.raises(kind, match="nothing-here"):
            load(gone)
