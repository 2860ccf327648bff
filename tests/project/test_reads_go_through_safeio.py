"""Every file the product reads goes through `noisefeat.safeio` (issue 42): a walk of the
four packages' code finds each call that reads a file by path, and fails on one that is not
on the list below with its reason. Control: the walk finds a call planted in a module."""
from __future__ import annotations

import ast
from pathlib import Path

PACKAGES = ("noisefeat", "learning", "renderer", "service")
#: methods and functions that read a file by name (Path.read_text, numpy, safetensors, zip)
READERS = {"read_bytes", "read_text", "load_file", "ZipFile", "fromfile", "loadtxt", "genfromtxt", "memmap",
           "safe_open"}
LOADERS = {"np", "numpy", "json", "pickle", "torch"}
#: (module, call) pairs that read a file object or bytes safeio opened, or hand a checked path on
ALLOWED = {
    ("learning/data/npz.py", "ZipFile"): "a file object from safeio.open_input",
    ("learning/models/bundle_check.py", "ZipFile"): "bytes from safeio.read_input, or an archive being written",
    ("learning/models/transfer.py", "torch.load"): "bytes from safeio.read_input",
    ("renderer/scenes.py", "load_file"): "Mitsuba reads the XML and what it names after renderer.scenefiles checked them",
}


def reads(source: str) -> list[tuple[int, str]]:
    """(line, call) of every call in `source` that reads a file by path."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Call):
            continue
        f = node.func
        if isinstance(f, ast.Name) and f.id == "open":
            mode = node.args[1] if len(node.args) > 1 else next((k.value for k in node.keywords if k.arg == "mode"),
                                                                None)
            if not (isinstance(mode, ast.Constant) and any(c in str(mode.value) for c in "wax")):
                found.append((node.lineno, "open"))
        elif isinstance(f, ast.Attribute):
            owner = f.value.id if isinstance(f.value, ast.Name) else None
            if f.attr == "load" and owner in LOADERS:
                found.append((node.lineno, f"{owner}.load"))
            elif f.attr in READERS:
                found.append((node.lineno, f.attr))
    return found


def test_every_read_goes_through_safeio() -> None:
    root = Path(__file__).parents[2]
    every = [(str(path.relative_to(root)), line, call) for pkg in PACKAGES for path in sorted((root / pkg).rglob("*.py"))
             for line, call in reads(path.read_text(encoding="utf-8"))]
    outside = [f"{where}:{line}: {call}" for where, line, call in every if (where, call) not in ALLOWED]
    assert not outside, "files read outside noisefeat.safeio:\n" + "\n".join(outside)
    assert set(ALLOWED) == {(where, call) for where, _, call in every}, "an allowed read is gone: drop its entry"


def test_the_walk_finds_a_planted_read() -> None:
    planted = "import numpy as np\nfrom pathlib import Path\n\ndef f(p):\n    x = np.load(p)\n" \
              "    return Path(p).read_bytes(), open(p).read(), open(p, 'wb')\n"
    assert [c for _, c in reads(planted)] == ["np.load", "read_bytes", "open"]
