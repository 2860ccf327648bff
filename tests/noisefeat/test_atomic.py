"""noisefeat.atomic: the one atomic-write helper, and nothing else renames files into place."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

from noisefeat.atomic import atomic_path, atomic_write, is_temporary
from tests.support import ROOT

PACKAGES = ("noisefeat", "learning", "renderer", "service")


def test_atomic_write_bytes_str_and_callable(tmp_path: Path) -> None:
    assert atomic_write(tmp_path / "a" / "b.bin", b"\x00\x01") == tmp_path / "a" / "b.bin"
    assert (tmp_path / "a" / "b.bin").read_bytes() == b"\x00\x01"
    atomic_write(tmp_path / "t.txt", "héllo")
    assert (tmp_path / "t.txt").read_text("utf-8") == "héllo"
    seen: list[Path] = []
    atomic_write(tmp_path / "plot.png", lambda p: (seen.append(p), p.write_bytes(b"png")))
    assert seen[0].suffix == ".png" and is_temporary(seen[0].name)   # writers that pick a format by suffix
    assert (tmp_path / "plot.png").read_bytes() == b"png"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "plot.png", "t.txt"]


def test_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path: Path) -> None:
    target = tmp_path / "f.json"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["f.json"]


def test_no_hand_written_rename_outside_the_helper() -> None:
    """Every write that renames a temporary file into place goes through noisefeat.atomic."""
    found = []
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            if path == ROOT / "noisefeat" / "atomic.py":
                continue
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                        and node.func.attr in ("replace", "rename") and isinstance(node.func.value, ast.Name)):
                    continue
                owner = node.func.value.id
                if owner == "os" or "tmp" in owner.lower():     # os.replace(tmp, p), tmp.replace(p)
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not found, f"renames outside noisefeat.atomic: {found}"
