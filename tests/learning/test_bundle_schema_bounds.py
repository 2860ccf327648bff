"""A model.skops's schema is bounded and its attributes known: a schema of 88 MB
of nodes within the file caps was accepted (`render --model` peaked at 1.1 GB against
0.47 GB), and an attribute no noisestop estimator has was loaded as it came. Both are
refused in one line naming the file, the schema before skops parses it."""
from __future__ import annotations

import hashlib
import io
import json
import zipfile
from pathlib import Path
from typing import Any, Callable

import pytest

from learning.models.bundle import load_model
from learning.models.bundle_check import MAX_SCHEMA_BYTES, MAX_SCHEMA_NODES
from tests.support.demo import make_demo_bundle


def _json_node(value: int, ident: int) -> dict[str, Any]:
    return {"__class__": "int", "__module__": "builtins", "__loader__": "JsonNode", "content": str(value),
            "is_json": True, "__id__": ident}


def _list_node(items: list[dict[str, Any]], ident: int) -> dict[str, Any]:
    return {"__class__": "list", "__module__": "builtins", "__loader__": "ListNode", "content": items,
            "__id__": ident}


def _bundle(tmp_path: Path, change: Callable[[dict[str, Any]], None]) -> Path:
    """A demo bundle whose estimator's attributes (the schema's top object) `change` edits;
    the manifest's model hash follows, as a forger's would."""
    path = make_demo_bundle(tmp_path / "bundle")
    model = path / "model.skops"
    with zipfile.ZipFile(model) as zf:
        members = [(info, zf.read(info)) for info in zf.infolist()]
    tree = json.loads(dict((i.filename, d) for i, d in members)["schema.json"])
    attrs = tree["content"]                     # a DictNode: its keys' types are listed beside them
    before = list(attrs["content"])
    change(attrs["content"])
    types = attrs["key_types"]["content"]
    types += [types[0]] * (len(attrs["content"]) - len(before))
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as zf:
        for info, data in members:
            zf.writestr(info, json.dumps(tree).encode() if info.filename == "schema.json" else data)
    model.write_bytes(out.getvalue())
    manifest = json.loads((path / "manifest.json").read_text())
    if manifest.get("model_sha256"):
        manifest["model_sha256"] = hashlib.sha256(out.getvalue()).hexdigest()
        (path / "manifest.json").write_text(json.dumps(manifest))
    return path


def test_an_intact_bundle_loads(tmp_path: Path) -> None:
    load_model(_bundle(tmp_path, lambda attrs: None))


def test_a_schema_of_too_many_nodes_is_refused(tmp_path: Path) -> None:
    """Small in bytes (a node is ~100), past the node bound: in a known attribute."""
    n = MAX_SCHEMA_NODES + 1
    path = _bundle(tmp_path, lambda attrs: attrs.__setitem__(
        "class_weight", _list_node([_json_node(0, 7)] * n, 8)))
    with pytest.raises(ValueError, match="schema") as err:
        load_model(path)
    assert str(path / "model.skops") in str(err.value) and "nodes" in str(err.value)


def test_a_schema_of_too_many_bytes_is_refused(tmp_path: Path) -> None:
    big = "x" * (MAX_SCHEMA_BYTES + 1)
    path = _bundle(tmp_path, lambda attrs: attrs.__setitem__(
        "class_weight", {**_json_node(0, 7), "__class__": "str", "content": json.dumps(big)}))
    with pytest.raises(ValueError, match="schema") as err:
        load_model(path)
    assert str(path / "model.skops") in str(err.value) and "bytes" in str(err.value)


def test_an_unknown_attribute_is_refused(tmp_path: Path) -> None:
    path = _bundle(tmp_path, lambda attrs: attrs.__setitem__("payload_", _list_node([_json_node(1, 7)], 8)))
    with pytest.raises(ValueError, match="payload_") as err:
        load_model(path)
    assert str(path / "model.skops") in str(err.value) and "unknown attribute" in str(err.value)
