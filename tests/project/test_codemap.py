"""docs/codemap.md names every room: each module of the four packages, of the benchmarks and
of the examples, and each sub-package, appears (as `name`, or `name/` for a sub-package) in its package's part
of the map (the section headed by the package's name), so a newcomer can find any file from
the docs."""
from __future__ import annotations

import re
from pathlib import Path

from tests.support import ROOT

ROOMS = ("noisefeat", "learning", "renderer", "service", "benchmarks", "examples")
CODEMAP = ROOT / "docs" / "codemap.md"


def map_parts(text: str) -> dict[str, str]:
    """Package -> its part of the map: from its heading (`## `name`...`) to the next heading
    of that level."""
    parts: dict[str, str] = {}
    for chunk in re.split(r"\n(?=## )", text):
        if m := re.match(r"## `(\w+)`", chunk):
            parts[m.group(1)] = chunk
    return parts


def unmapped(root: Path, text: str, rooms: tuple[str, ...] = ROOMS) -> list[str]:
    """Modules (and sub-packages) under `rooms` that their package's part does not name."""
    parts = map_parts(text)
    missing = []
    for pkg in rooms:
        part = parts.get(pkg, "")
        for path in sorted((root / pkg).rglob("*.py")):
            rel = path.relative_to(root)
            if path.stem != "__init__":
                if f"`{path.stem}`" not in part:
                    missing.append(str(rel))
            elif path.parent != root / pkg and f"`{path.parent.name}/`" not in part:
                missing.append(f"{rel.parent}/")
    return missing


def test_the_map_names_every_module() -> None:
    text = CODEMAP.read_text()
    assert set(ROOMS) <= set(map_parts(text))
    assert sum(1 for pkg in ROOMS for _ in (ROOT / pkg).rglob("*.py")) > 100
    assert unmapped(ROOT, text) == []


def test_the_readme_links_the_map() -> None:
    assert "docs/codemap.md" in (ROOT / "README.md").read_text()


def test_the_checker_sees_a_room_left_out(tmp_path) -> None:
    """Control: a module named in another package's part only, a sub-package named without
    its slash and a package without a part are each reported."""
    for rel in ("renderer/__init__.py", "renderer/api.py", "renderer/budget.py", "benchmarks/openloop.py",
                "learning/data/__init__.py", "learning/data/stack.py"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("")
    text = ("# Map of the code\n\n## `renderer`: Mitsuba\n\n| rooms | what |\n|---|---|\n"
            "| `api` | renderer.render |\n\n## `learning`\n\n* `data`: `stack`; `budget`\n\n"
            "## Next\n`openloop`\n")
    assert unmapped(tmp_path, text, ("renderer", "learning", "benchmarks")) == [
        "renderer/budget.py", "learning/data/", "benchmarks/openloop.py"]
