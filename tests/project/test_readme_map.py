"""README's "Map of the code" names every room: each module of the four packages and of the
benchmarks, and each sub-package, appears (as `name`, or `name/` for a sub-package) in its
package's row, so a newcomer can find any file from the README."""
from __future__ import annotations

import re
from pathlib import Path

from tests.support import ROOT

ROOMS = ("noisefeat", "learning", "renderer", "service", "benchmarks")


def map_rows(readme: str) -> dict[str, str]:
    """Package -> its row of the map table (the section "Map of the code")."""
    section = readme.split("## Map of the code", 1)[1].split("\n## ", 1)[0]
    return {m.group(1): line for line in section.splitlines() if (m := re.match(r"\| `(\w+)`", line))}


def unmapped(root: Path, readme: str, rooms: tuple[str, ...] = ROOMS) -> list[str]:
    """Modules (and sub-packages) under `rooms` that their package's row does not name."""
    rows = map_rows(readme)
    missing = []
    for pkg in rooms:
        row = rows.get(pkg, "")
        for path in sorted((root / pkg).rglob("*.py")):
            rel = path.relative_to(root)
            if path.stem != "__init__":
                if f"`{path.stem}`" not in row:
                    missing.append(str(rel))
            elif path.parent != root / pkg and f"`{path.parent.name}/`" not in row:
                missing.append(f"{rel.parent}/")
    return missing


def test_the_map_names_every_module() -> None:
    readme = (ROOT / "README.md").read_text()
    assert set(ROOMS) <= set(map_rows(readme))
    assert sum(1 for pkg in ROOMS for _ in (ROOT / pkg).rglob("*.py")) > 100
    assert unmapped(ROOT, readme) == []


def test_the_checker_sees_a_room_left_out(tmp_path) -> None:
    """Control: a module named in another package's row only, a sub-package named without
    its slash and a package without a row are each reported."""
    for rel in ("renderer/__init__.py", "renderer/api.py", "renderer/budget.py", "benchmarks/openloop.py",
                "learning/data/__init__.py", "learning/data/stack.py"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("")
    readme = ("# x\n\n## Map of the code\n\n| package | rooms |\n|---|---|\n"
              "| `renderer` (Mitsuba) | `api`: renderer.render |\n"
              "| `learning` | `data`: `stack`; `budget` |\n\n## Next\n`openloop`\n")
    assert unmapped(tmp_path, readme, ("renderer", "learning", "benchmarks")) == [
        "renderer/budget.py", "learning/data/", "benchmarks/openloop.py"]
