"""What one `renderer.render` with flip touches (issue 52's "render path"): the project's
files in which a function runs during the render, after `import renderer`, with their
lines. Module and class bodies run by an import inside the render are not counted (what a
reader follows is the calls: only functions, `inspect.CO_OPTIMIZED`), nor are the benchmarks. `python -m benchmarks.render_path`.
"""
from __future__ import annotations

import inspect
import sys
import threading
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("noisefeat", "learning", "renderer", "service")


def render_path(scene: str = "cornell", resolution: int = 64, max_spp: int = 64) -> dict[str, Any]:
    """{file: lines} of the files a flip render of `scene` runs functions in, and totals."""
    import renderer

    roots = tuple(str(ROOT / p) + "/" for p in PACKAGES)
    seen: set[str] = set()

    def profile(frame: Any, event: str, _arg: Any) -> None:
        code = frame.f_code
        if event == "call" and code.co_flags & inspect.CO_OPTIMIZED and code.co_filename.startswith(roots):
            seen.add(code.co_filename)
    sys.setprofile(profile)
    threading.setprofile(profile)
    try:
        renderer.render(scene, criterion="flip", resolution=resolution, max_spp=max_spp, progress=False)
    finally:
        sys.setprofile(None)
        threading.setprofile(None)
    files = {str(Path(f).relative_to(ROOT)): len(Path(f).read_text().splitlines()) for f in sorted(seen)}
    ren = {f: n for f, n in files.items() if f.startswith("renderer/")}
    return {"files": files, "total": {"files": len(files), "lines": sum(files.values())},
            "renderer": {"files": len(ren), "lines": sum(ren.values())},
            "renderer_folder_lines": sum(len(p.read_text().splitlines()) for p in (ROOT / "renderer").rglob("*.py"))}


if __name__ == "__main__":
    r = render_path()
    for f, n in r["files"].items():
        print(f"{n:5d} {f}")
    print(f"render path: {r['total']['files']} files, {r['total']['lines']} lines; in renderer/: "
          f"{r['renderer']['files']} files, {r['renderer']['lines']} lines; renderer/ holds "
          f"{r['renderer_folder_lines']} lines")
