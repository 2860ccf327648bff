"""Every file the product reads goes through `noisefeat.safeio`: a walk of the
four packages' code finds each call that reads a file by path, and fails on one that is not
on the list below with its reason. Image libraries count too (Pillow, imageio, OpenEXR and
any `imread`): they open a path themselves unless handed bytes safeio read. Controls: the
walk finds calls planted in a module, whatever name the library is bound to."""
from __future__ import annotations

import ast
from pathlib import Path

from tests.support import ROOT

PACKAGES = ("noisefeat", "learning", "renderer", "service")
#: methods and functions that read a file by name (Path.read_text, numpy, safetensors, zip)
READERS = {"read_bytes", "read_text", "load_file", "ZipFile", "fromfile", "loadtxt", "genfromtxt", "memmap",
           "safe_open"}
LOADERS = {"np", "numpy", "json", "pickle", "torch"}
#: image libraries' calls that open a file by path, by qualified name (the module as imported,
#: or as `noisefeat.extras.require` or a function returning it loads it)
LIBRARY_READERS = {"PIL.Image.open", "OpenEXR.InputFile", "OpenEXR.File", "imageio.imread", "imageio.mimread",
                   "imageio.volread", "imageio.imopen", "imageio.get_reader", "imageio.v2.imread",
                   "imageio.v2.mimread", "imageio.v2.volread", "imageio.v2.get_reader", "imageio.v3.imread",
                   "imageio.v3.imopen", "imageio.v3.imiter"}
#: reader names that open a path whatever library they come from (cv2, tifffile, skimage.io, ...)
IMAGE_READERS = {"imread", "mimread", "volread", "imopen"}
#: what loads a module by its name as a string
MODULE_LOADERS = {"require", "import_module"}
#: (module, call) pairs that read a file object or bytes safeio opened, or hand a checked path on
ALLOWED = {
    ("learning/data/npz.py", "ZipFile"): "a file object from safeio.open_input",
    ("learning/data/exr.py", "OpenEXR.File"): "bytes from safeio.read_input (the other call builds a file in "
                                              "memory that atomic_write writes)",
    ("learning/data/exr.py", "PIL.Image.open"): "bytes from safeio.read_input",
    ("learning/models/bundle_check.py", "ZipFile"): "bytes from safeio.read_input, or an archive being written",
    ("learning/models/transfer_weights.py", "torch.load"): "bytes from safeio.read_input",
    ("renderer/scenes/catalog.py", "load_file"): "Mitsuba reads the XML and what it names after renderer.scenes.scenefiles checked them",
}


def _dotted(node: ast.AST) -> str | None:
    """`a.b.c` of a Name or an Attribute chain on one, else None."""
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        base = _dotted(node.value)
        return None if base is None else f"{base}.{node.attr}"
    return None


def _loaded_module(call: ast.AST) -> str | None:
    """The module a `require("X")` or `importlib.import_module("X")` call loads, else None."""
    if not (isinstance(call, ast.Call) and call.args and isinstance(call.args[0], ast.Constant)
            and isinstance(call.args[0].value, str)):
        return None
    name = _dotted(call.func)
    return call.args[0].value if name and name.rsplit(".", 1)[-1] in MODULE_LOADERS else None


def aliases(tree: ast.AST) -> tuple[dict[str, str], dict[str, str]]:
    """(name -> module, function -> module it returns) of a module: names bound by imports,
    by `require("X")` / `import_module("X")`, or by calling a function that returns one."""
    names: dict[str, str] = {}
    returns: dict[str, str] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                names[a.asname or a.name.split(".")[0]] = a.name if a.asname else a.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            for a in node.names:
                names[a.asname or a.name] = f"{node.module}.{a.name}"
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for sub in ast.walk(node):
                if isinstance(sub, ast.Return) and (mod := _loaded_module(sub.value)):
                    returns[node.name] = mod
    for node in ast.walk(tree):              # after `returns` is known: `exr = _openexr()`
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
            value = node.value
            mod = _loaded_module(value) or (returns.get(value.func.id) if isinstance(value, ast.Call)
                                            and isinstance(value.func, ast.Name) else None)
            if mod:
                names[node.targets[0].id] = mod
    return names, returns


def _qualified(node: ast.AST, names: dict[str, str], returns: dict[str, str]) -> str | None:
    """The qualified name a call's target stands for (`image.open` -> `PIL.Image.open`)."""
    if isinstance(node, ast.Name):
        return names.get(node.id, node.id)
    if isinstance(node, ast.Attribute):
        base = _qualified(node.value, names, returns)
        return None if base is None else f"{base}.{node.attr}"
    if isinstance(node, ast.Call):
        if isinstance(node.func, ast.Name) and node.func.id in returns:
            return returns[node.func.id]
        return _loaded_module(node)
    return None


def reads(source: str) -> list[tuple[int, str]]:
    """(line, call) of every call in `source` that reads a file by path."""
    found = []
    tree = ast.parse(source)
    names, returns = aliases(tree)
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        f = node.func
        qualified = _qualified(f, names, returns)
        if qualified in LIBRARY_READERS or (qualified or "").rsplit(".", 1)[-1] in IMAGE_READERS:
            found.append((node.lineno, qualified))
        elif isinstance(f, ast.Name) and f.id == "open":
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


def every_read(root: Path) -> list[tuple[str, int, str]]:
    """(module path, line, call) of every read by path in the four packages under `root`."""
    return [(str(path.relative_to(root)), line, call) for pkg in PACKAGES for path in sorted((root / pkg).rglob("*.py"))
            for line, call in reads(path.read_text(encoding="utf-8"))]


def outside(root: Path) -> list[str]:
    """The reads under `root` that are not on the ALLOWED list, one line each."""
    return [f"{where}:{line}: {call}" for where, line, call in every_read(root) if (where, call) not in ALLOWED]


def test_every_read_goes_through_safeio() -> None:
    found = outside(ROOT)
    assert not found, "files read outside noisefeat.safeio:\n" + "\n".join(found)
    assert set(ALLOWED) == {(where, call) for where, _, call in every_read(ROOT)}, \
        "an allowed read is gone: drop its entry"


def test_the_walk_finds_a_planted_read() -> None:
    planted = "import numpy as np\nfrom pathlib import Path\n\ndef f(p):\n    x = np.load(p)\n" \
              "    return Path(p).read_bytes(), open(p).read(), open(p, 'wb')\n"
    assert [c for _, c in reads(planted)] == ["np.load", "read_bytes", "open"]


#: a module opening images by path through each library, under the names code binds them to
PLANTED_LIBRARIES = """\
import OpenEXR
import PIL.Image
import imageio
import imageio.v3 as iio
from PIL import Image
from imageio.v2 import imread as read_image

from noisefeat.extras import require


def _openexr():
    return require("OpenEXR")


def f(p):
    exr = _openexr()
    pil = require("PIL.Image")
    import cv2
    return (Image.open(p), PIL.Image.open(p), pil.open(p), imageio.imread(p), iio.imread(p), read_image(p),
            OpenEXR.InputFile(p), OpenEXR.File(p), exr.File(p), require("PIL.Image").open(p), cv2.imread(p))
"""
PLANTED_CALLS = ["PIL.Image.open", "PIL.Image.open", "PIL.Image.open", "imageio.imread", "imageio.v3.imread",
                 "imageio.v2.imread", "OpenEXR.InputFile", "OpenEXR.File", "OpenEXR.File", "PIL.Image.open",
                 "cv2.imread"]


def test_the_walk_finds_planted_library_reads(tmp_path) -> None:
    """Control: Pillow, imageio, OpenEXR and cv2 opening a path, imported or loaded by
    `require` (directly, or through a function returning it, as learning/data/exr.py binds
    them), are each found by the walk of a package tree; the same module without them is
    clean, and the library's other calls (Image.fromarray, OpenEXR constants) are not reads."""
    assert [c for _, c in reads(PLANTED_LIBRARIES)] == PLANTED_CALLS
    module = tmp_path / "learning" / "data" / "planted.py"
    module.parent.mkdir(parents=True)
    module.write_text(PLANTED_LIBRARIES)
    assert [line.split(": ", 1)[1] for line in outside(tmp_path)] == PLANTED_CALLS
    module.write_text("from PIL import Image\nimport OpenEXR\n\ndef g(a):\n"
                      "    return Image.fromarray(a), OpenEXR.PIZ_COMPRESSION\n")
    assert outside(tmp_path) == []


def test_an_allowed_module_is_allowed_only_its_own_call(tmp_path) -> None:
    """Control: learning/data/exr.py may decode bytes with Pillow and OpenEXR, but an
    imageio read planted there is still reported."""
    module = tmp_path / "learning" / "data" / "exr.py"
    module.parent.mkdir(parents=True)
    module.write_text("import io\nfrom PIL import Image\nimport imageio.v3 as iio\n\ndef r(data, p):\n"
                      "    return Image.open(io.BytesIO(data)), iio.imread(p)\n")
    assert outside(tmp_path) == ["learning/data/exr.py:6: imageio.v3.imread"]
