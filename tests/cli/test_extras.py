"""Install by parts: a missing optional package is one line naming the extra that brings it
(`pip install 'noisestop[render]'`), from the Python API (MissingExtra, an ImportError) and
from the command line (exit 2, no traceback); pyproject's extras hold what the code imports."""
from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from noisefeat.extras import EXTRA_OF, PACKAGES_OF, MissingExtra, missing_extra, require, require_extra
from tests.support import ROOT

PACKAGES = ("noisefeat", "learning", "renderer", "service")


def test_require_names_the_extra(monkeypatch):
    assert require("json").dumps(1) == "1"
    cases = {"mitsuba": "render", "drjit": "render", "matplotlib": "render", "fastapi": "serve",
             "uvicorn": "serve", "flip_evaluator": "data", "dask": "data", "torchvision": "transfer"}
    for module, extra in cases.items():
        monkeypatch.setitem(sys.modules, module, None)
        with pytest.raises(MissingExtra, match=re.escape(f"pip install 'noisestop[{extra}]'")) as info:
            require(module)
        assert isinstance(info.value, ImportError) and info.value.extra == extra
        assert str(info.value).startswith(f"{module} is not installed; it comes with the [{extra}] extra")


def test_a_dependency_of_a_dotted_module_and_plain_import_errors(monkeypatch):
    for name in ("dask", "dask.distributed"):       # earlier tests may have imported both
        monkeypatch.setitem(sys.modules, name, None)
    with pytest.raises(MissingExtra, match=r"dask is not installed.*noisestop\[data\]"):
        require("dask.distributed")
    with pytest.raises(MissingExtra, match=r"^the plots need matplotlib, which is not installed"):
        for name in ("matplotlib", "matplotlib.figure"):
            monkeypatch.setitem(sys.modules, name, None)
        require("matplotlib.figure", purpose="the plots")
    with pytest.raises(ModuleNotFoundError) as info:
        require("no_such_package_anywhere")
    assert not isinstance(info.value, MissingExtra)
    plain = ModuleNotFoundError("No module named 'uvicorn'", name="uvicorn")
    assert "noisestop[serve]" in str(missing_extra(plain))
    assert missing_extra(ModuleNotFoundError("x", name="unrelated")) is None
    assert missing_extra(ValueError("x")) is None


def test_require_extra_checks_each_package(monkeypatch):
    require_extra("serve")
    monkeypatch.setitem(sys.modules, "h11", None)
    with pytest.raises(MissingExtra, match=r"h11 is not installed.*noisestop\[serve\]"):
        require_extra("serve")


def _blocked_cli(blocked: tuple[str, ...], *argv: str, tmp_path: Path) -> subprocess.CompletedProcess:
    """`noisestop argv` in a fresh process where the `blocked` packages cannot be imported."""
    code = (f"import sys\nfor m in {list(blocked)!r}: sys.modules[m] = None\n"
            "from service.cli import main\nsys.exit(main(sys.argv[1:]))")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("NOISESTOP_DEBUG", None)
    return subprocess.run([sys.executable, "-c", code, *argv], cwd=tmp_path, capture_output=True,
                          text=True, timeout=300, env=env)


@pytest.mark.parametrize("blocked, argv, extra", [
    (("mitsuba", "drjit"), ("render", "--scene", "cornell", "--out", "r", "--max-spp", "4", "--criterion", "uniform"), "render"),
    (("fastapi", "starlette"), ("serve", "--port", "0"), "serve"),
    (("uvicorn",), ("serve", "--port", "0"), "serve"),
    (("dask", "distributed"), ("dataset", "build", "--out", "d", "--scenes", "cornell", "--resolution", "32",
                               "--step", "4", "--levels", "1", "--reference-spp", "8", "--workers", "1"), "data"),
], ids=["render", "serve-fastapi", "serve-uvicorn", "data"])
def test_the_command_line_says_which_extra_in_one_line(tmp_path, blocked, argv, extra):
    out = _blocked_cli(blocked, *argv, tmp_path=tmp_path)
    lines = [line for line in out.stderr.splitlines() if line.strip() and "%|" not in line
             and " INFO " not in line and " WARNING " not in line]
    assert out.returncode == 2, out.stderr
    assert "Traceback" not in out.stderr and len(lines) == 1, out.stderr
    assert lines[0].startswith(f"noisestop {argv[0]}: error: ") and "unexpected" not in lines[0], lines[0]
    assert lines[0].endswith(f"pip install 'noisestop[{extra}]'"), lines[0]


# ----------------------------------------------------------------------------- pyproject

def _requirement_name(req: str) -> str:
    return re.split(r"[\s\[<>=!~;]", req, maxsplit=1)[0].lower().replace("_", "-")


#: the source checkout's own top-level folders (not third-party, not installed)
CHECKOUT = ("benchmarks", "examples", "tests")


def _third_party_imports(packages: tuple[str, ...] = PACKAGES) -> dict[str, set[str]]:
    """Top-level import name -> the project's files importing it (anywhere in the file)."""
    stdlib = set(sys.stdlib_module_names)
    found: dict[str, set[str]] = {}
    for pkg in packages:
        for path in (ROOT / pkg).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                names = []
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
                    names = [node.module]
                elif (isinstance(node, ast.Call) and getattr(node.func, "id", None) == "require"
                      and node.args and isinstance(node.args[0], ast.Constant)):
                    names = [node.args[0].value]
                for name in names:
                    top = name.split(".")[0]
                    if top not in stdlib and top not in PACKAGES + CHECKOUT and top != "__future__":
                        found.setdefault(top, set()).add(str(path.relative_to(ROOT)))
    return found


#: import name -> distribution name on PyPI, where they differ
DISTRIBUTION = {"sklearn": "scikit-learn", "pywt": "pywavelets", "PIL": "pillow", "OpenEXR": "openexr",
                "flip_evaluator": "flip-evaluator", "prometheus_fastapi_instrumentator":
                "prometheus-fastapi-instrumentator", "dask": "dask"}
#: imported, but brought by a listed package (of the same extra)
TRANSITIVE = {"pydantic_core": "pydantic", "starlette": "fastapi", "anyio": "fastapi",
              "prometheus_client": "prometheus-fastapi-instrumentator", "distributed": "dask"}
#: developer tools, imported only by benchmark sections (benchmarks/, outside the installed packages) that
#: need [dev]
DEV_ONLY = {"schemathesis", "hypothesis"}


def test_every_import_is_in_the_core_or_its_extra():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    core = {_requirement_name(r) for r in project["dependencies"]}
    extras = {k: {_requirement_name(r) for r in v} for k, v in project["optional-dependencies"].items()}
    assert set(PACKAGES_OF) | {"all", "dev", "docs"} == set(extras)       # dev and docs: tools, imported by none
    assert extras["all"] == {"noisestop"} and "render,serve,data,transfer" in str(
        project["optional-dependencies"]["all"])
    for name, files in _third_party_imports().items():
        assert name not in DEV_ONLY, (name, "a developer tool imported by an installed package", files)
        dist = TRANSITIVE.get(name) or DISTRIBUTION.get(name, name).lower()
        extra = EXTRA_OF.get(name)
        if extra:
            assert dist in extras[extra], (name, extra)
            assert dist not in core, (name, "is optional but a core dependency")
        else:
            assert dist in core, (name, "imported but not a core dependency", files)
    for extra, modules in PACKAGES_OF.items():
        assert all(EXTRA_OF[m] == extra for m in modules)
    bench = _third_party_imports(("benchmarks", "examples"))     # the checkout's code: what [all] and [dev] bring
    assert DEV_ONLY <= set(bench)                  # the scan sees the developer tools where they are
    every_extra = set().union(*extras.values())
    for name, files in bench.items():
        dist = TRANSITIVE.get(name) or DISTRIBUTION.get(name, name).lower()
        assert name in DEV_ONLY or dist in core | every_extra, (name, "imported by the benchmarks", files)
