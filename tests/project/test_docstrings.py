"""DESIGN's Python API names document every parameter (numpy style) and what they return."""
from __future__ import annotations

import inspect
import re

import pytest

import learning
import noisefeat

API = {
    "noisefeat.split_blocks": noisefeat.split_blocks,
    "noisefeat.extract_features": noisefeat.extract_features,
    "noisefeat.FeatureBase": noisefeat.FeatureBase,
    "noisefeat.FeatureBase.forward": noisefeat.FeatureBase.forward,
    "learning.read_stack": learning.read_stack,
    "learning.write_stack": learning.write_stack,
    "learning.load_model": learning.load_model,
}


def _documented(doc: str) -> set[str]:
    """Names listed under a numpy-style 'Parameters' heading."""
    section = doc.split("Parameters\n", 1)[1]
    section = re.split(r"\n\s*(Returns|Yields|Raises|Attributes)\n", section)[0]
    return {m.group(1).lstrip("*") for m in re.finditer(r"^\s*(\**\w+)\s*(?::|$)", section, re.M)}


@pytest.mark.parametrize("name", sorted(API))
def test_every_parameter_is_documented(name: str) -> None:
    obj = API[name]
    doc = inspect.getdoc(obj) or ""
    assert "Parameters\n----------" in doc, name
    assert ("Returns\n-------" in doc) != inspect.isclass(obj), name   # classes: Attributes instead
    params = [p for p in inspect.signature(obj).parameters if p != "self"]
    missing = set(params) - _documented(doc)
    assert not missing, f"{name}: undocumented parameters {sorted(missing)}"
