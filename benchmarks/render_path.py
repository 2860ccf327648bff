"""What one `renderer.render` with flip touches (its "render path"): the project's
files in which a function runs during the render, after `import renderer`, with their
lines. Module and class bodies run by an import inside the render are not counted (what a
reader follows is the calls: only functions, `inspect.CO_OPTIMIZED`), nor are the benchmarks.
`python -m benchmarks.render_path`.

It also lists the modules that act on the `tile` setting during that render (`tile_modules`):
those where a function that ran names it, as a variable, parameter, keyword argument or
attribute called ``tile``, a ``["tile"]`` subscript or a comparison with ``"tile"`` (a
report's ``"tile"`` key, an output name, is not reading the setting). The fewer, the fewer
places a reader must visit to know what a tile does.
"""
from __future__ import annotations

import ast
import inspect
import sys
import threading
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("noisefeat", "learning", "renderer", "service")
SETTING = "tile"


def names_setting(node: ast.AST, setting: str = SETTING) -> bool:
    """Whether `node` reads `setting` (see the module docstring)."""
    if isinstance(node, ast.Name):
        return node.id == setting
    if isinstance(node, ast.Attribute):
        return node.attr == setting
    if isinstance(node, (ast.keyword, ast.arg)):
        return node.arg == setting
    if isinstance(node, ast.Subscript):
        return isinstance(node.slice, ast.Constant) and node.slice.value == setting
    if isinstance(node, ast.Compare):
        return any(isinstance(c, ast.Constant) and c.value == setting for c in (node.left, *node.comparators))
    return False


def acting_lines(path: Path, ran: set[int], setting: str = SETTING) -> list[int]:
    """Lines of `path` where a function that ran (by its first line, as `co_firstlineno`
    gives it) reads `setting`; nested functions count with the one around them."""
    lines: set[int] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            first = min([node.lineno, *(d.lineno for d in node.decorator_list)])
            if first in ran:
                lines |= {getattr(n, "lineno", node.lineno) for n in ast.walk(node) if names_setting(n, setting)}
    return sorted(lines)


def render_path(scene: str = "cornell", resolution: int = 64, max_spp: int = 64) -> dict[str, Any]:
    """{file: lines} of the files a flip render of `scene` runs functions in, the modules
    acting on `tile` there ({file: the lines}), and totals."""
    import renderer

    roots = tuple(str(ROOT / p) + "/" for p in PACKAGES)
    ran: dict[str, set[int]] = {}

    def profile(frame: Any, event: str, _arg: Any) -> None:
        code = frame.f_code
        if event == "call" and code.co_flags & inspect.CO_OPTIMIZED and code.co_filename.startswith(roots):
            ran.setdefault(code.co_filename, set()).add(code.co_firstlineno)
    sys.setprofile(profile)
    threading.setprofile(profile)
    try:
        renderer.render(scene, criterion="flip", resolution=resolution, max_spp=max_spp, progress=False)
    finally:
        sys.setprofile(None)
        threading.setprofile(None)
    files = {str(Path(f).relative_to(ROOT)): len(Path(f).read_text().splitlines()) for f in sorted(ran)}
    ren = {f: n for f, n in files.items() if f.startswith("renderer/")}
    tile = {str(Path(f).relative_to(ROOT)): lines for f in sorted(ran) if (lines := acting_lines(Path(f), ran[f]))}
    return {"files": files, "total": {"files": len(files), "lines": sum(files.values())},
            "renderer": {"files": len(ren), "lines": sum(ren.values())},
            "tile_modules": tile,
            "renderer_folder_lines": sum(len(p.read_text().splitlines()) for p in (ROOT / "renderer").rglob("*.py"))}


if __name__ == "__main__":
    r = render_path()
    for f, n in r["files"].items():
        print(f"{n:5d} {f}")
    for f, lines in r["tile_modules"].items():
        print(f"tile: {f} (lines {', '.join(map(str, lines))})")
    print(f"render path: {r['total']['files']} files, {r['total']['lines']} lines; in renderer/: "
          f"{r['renderer']['files']} files, {r['renderer']['lines']} lines; renderer/ holds "
          f"{r['renderer_folder_lines']} lines; {len(r['tile_modules'])} modules act on {SETTING} "
          f"({sum(f.startswith('renderer/') for f in r['tile_modules'])} in renderer/)")
