"""The house rules, checked on the source: dependencies point one way (noisefeat <-
learning <- renderer <- service <- examples <- benchmarks, DESIGN.md, and inside learning its
sub-packages in the order of their jobs), in every import statement of a module, inside
functions too (a function-level import only hides an upward edge or a circle until the
function runs), and no modules import each other around a circle, among the packages and
among the benchmarks."""
from __future__ import annotations

import ast
from pathlib import Path
from tests.support import ROOT

PACKAGES = ("noisefeat", "learning", "renderer", "service")
#: the examples (`make run`'s demo) sit above the packages: they may import any of them, none
#: imports them
EXAMPLES = "examples"
#: the benchmarks sit above the packages and the examples: they may import any of them, none imports them
BENCHMARKS = "benchmarks"
#: learning's rooms, each importing only from those before it (learning/__init__.py)
LEARNING = {"names": 0, "stoprule": 0, "data": 1, "inputs": 2, "models": 3, "evaluation": 4, "training": 5}
#: renderer's rooms: a folder per job, each importing only the jobs named here and
#: the shared modules at the top; the shared modules import no job but the criteria; the
#: doors at the top (the package, api, plugin, render_many) may import any room
RENDERER_JOBS = {"client": set(), "criteria": {"client"}, "scenes": set(), "live": {"criteria", "scenes"},
                 "simulation": {"criteria", "live"}, "dataset": {"live", "scenes"}}
RENDERER_SHARED = {"spec", "settings", "setting_kinds", "plugin_schema", "errors", "farm"}
RENDERER_DOORS = {"api", "plugin", "render_many"}


def _modules(root: Path = ROOT, packages: tuple[str, ...] = PACKAGES) -> dict[str, Path]:
    out = {}
    for pkg in packages:
        for path in (root / pkg).rglob("*.py"):
            rel = path.relative_to(root).with_suffix("")
            parts = list(rel.parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


def _load_time_imports(name: str, path: Path, known: set[str], anywhere: bool = False) -> set[str]:
    """Modules of the project imported at module level (not inside functions), or with
    `anywhere` by any import statement of the file: inside functions, methods, `if` and
    `try` blocks too (relative imports resolved against the module's package)."""
    tree = ast.parse(path.read_text())
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found: set[str] = set()
    for node in (ast.walk(tree) if anywhere else tree.body):
        if isinstance(node, ast.If) and not anywhere:   # `if TYPE_CHECKING:` blocks are not load time
            continue
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            targets = [mod] + [f"{mod}.{a.name}" for a in node.names]
        else:
            continue
        for t in targets:
            while t and t not in known:
                t = t.rpartition(".")[0]
            if t and t != name:
                found.add(t)
    return found


def _graph(anywhere: bool = False, root: Path = ROOT,
           packages: tuple[str, ...] = PACKAGES) -> dict[str, set[str]]:
    mods = _modules(root, packages)
    known = set(mods)
    return {name: _load_time_imports(name, path, known, anywhere) for name, path in mods.items()}


def upward_imports(root: Path = ROOT,
                   packages: tuple[str, ...] = PACKAGES + (EXAMPLES, BENCHMARKS)) -> list[tuple[str, str]]:
    """(importer, imported) for every import statement anywhere in a module (load time,
    functions, methods, `if` and `try` blocks) that names a package later in `packages`."""
    rank = {pkg: i for i, pkg in enumerate(packages)}
    return sorted((a, b) for a, deps in _graph(anywhere=True, root=root, packages=packages).items() for b in deps
                  if rank[b.split(".")[0]] > rank[a.split(".")[0]])


def test_dependencies_point_one_way() -> None:
    assert len(_modules(packages=(BENCHMARKS,))) >= 18          # the benchmarks are in the graph
    assert "examples.showcase" in _modules(packages=(EXAMPLES,))   # and the examples
    assert upward_imports() == []


def test_the_checker_sees_an_upward_import_inside_a_function(tmp_path) -> None:
    """Control: a renderer module that imports the service only inside a method body (and
    a service module that imports the benchmarks inside a function) is found; the same
    imports at load time are found too, and a downward one is not."""
    for pkg in (*PACKAGES, BENCHMARKS):
        (tmp_path / pkg).mkdir()
        (tmp_path / pkg / "__init__.py").write_text("")
    (tmp_path / "service" / "app.py").write_text("def create():\n    return 1\n")
    (tmp_path / BENCHMARKS / "bench.py").write_text("from service.app import create\n")
    (tmp_path / "renderer" / "client.py").write_text(
        "import numpy as np\n\nclass C:\n    def m(self):\n        if True:\n"
        "            from service import app\n        return app\n")
    (tmp_path / "service" / "door.py").write_text("def f():\n    try:\n        import benchmarks.bench\n"
                                                 "    except ImportError:\n        pass\n")
    (tmp_path / "noisefeat" / "base.py").write_text("from learning import x\n")
    assert upward_imports(tmp_path) == [("noisefeat.base", "learning"), ("renderer.client", "service"),
                                        ("renderer.client", "service.app"), ("service.door", "benchmarks.bench")]
    # the old load-time reading missed both function-level ones
    load_time = _graph(root=tmp_path, packages=(*PACKAGES, BENCHMARKS))
    assert load_time["renderer.client"] == set() and load_time["service.door"] == set()


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Circles of load-time imports (a package's __init__ importing its own sub-modules aside)."""
    state: dict[str, int] = {}
    cycles: list[list[str]] = []

    def visit(node: str, stack: list[str]) -> None:
        state[node] = 1
        for dep in sorted(graph.get(node, ())):
            if state.get(dep) == 1:
                cycles.append(stack[stack.index(dep):] + [dep])
            elif dep not in state:
                visit(dep, stack + [dep])
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])
    return [c for c in cycles if not all(m == c[0] or m.startswith(c[0] + ".") or c[0].startswith(m + ".")
                                         for m in c)]


def test_no_import_circle() -> None:
    assert find_cycles(_graph()) == []


def test_no_import_circle_through_function_level_imports() -> None:
    """Every import statement anywhere in a module counts: a circle closed by an import
    inside a function is still a circle (optional imports such as Mitsuba's are edges too,
    and PEP 562 lazy names of a package's __init__ are not import statements)."""
    graph = _graph(anywhere=True)
    assert sum(map(len, graph.values())) > sum(map(len, _graph().values()))   # it sees more than load time
    assert find_cycles(graph) == []


def test_no_import_circle_among_the_benchmarks() -> None:
    """The benchmarks too, every import statement anywhere in their modules: they import
    each other mostly inside functions, which hid bench -> bench_native -> bench (and
    bench -> bench_cost -> bench) until the helper both need moved to marked_sections."""
    graph = _graph(anywhere=True, packages=PACKAGES + (BENCHMARKS,))
    ours = {m for m in graph if m.split(".")[0] == BENCHMARKS}
    assert len(ours) >= 18 and any(graph[m] & ours for m in ours)     # their edges among themselves are seen
    assert find_cycles(graph) == []


def test_the_checker_sees_a_circle_among_the_benchmarks(tmp_path) -> None:
    """Control: a planted benchmarks folder where bench imports a section at load time and
    the section imports bench back inside a function (the circle bench and bench_native
    had) is found; with the shared helper in a module both import, it is not."""
    for pkg in (*PACKAGES, BENCHMARKS):
        (tmp_path / pkg).mkdir()
        (tmp_path / pkg / "__init__.py").write_text("")
    bench = tmp_path / BENCHMARKS
    (bench / "bench.py").write_text("from .bench_native import md_native\n\n\ndef update_markdown(path, sections):\n"
                                    "    return None\n")
    (bench / "bench_native.py").write_text("def md_native(r):\n    return ''\n\n\ndef main():\n"
                                           "    from .bench import update_markdown\n    return update_markdown\n")
    packages = (*PACKAGES, BENCHMARKS)
    assert find_cycles(_graph(anywhere=True, root=tmp_path, packages=packages)) == [
        ["benchmarks.bench", "benchmarks.bench_native", "benchmarks.bench"]]
    assert find_cycles(_graph(root=tmp_path, packages=packages)) == []           # load time alone misses it
    (bench / "marked_sections.py").write_text("def update_markdown(path, sections):\n    return None\n")
    (bench / "bench.py").write_text("from .bench_native import md_native\nfrom .marked_sections import update_markdown\n")
    (bench / "bench_native.py").write_text("def md_native(r):\n    return ''\n\n\ndef main():\n"
                                           "    from .marked_sections import update_markdown\n    return update_markdown\n")
    assert find_cycles(_graph(anywhere=True, root=tmp_path, packages=packages)) == []


def test_the_checker_sees_a_circle(tmp_path) -> None:
    """Control: a made-up pair of modules importing each other is found."""
    known = {"a.x", "a.y", "a.z"}
    (tmp_path / "x.py").write_text("from a.y import f\n")
    (tmp_path / "y.py").write_text("from .z import g\n")
    (tmp_path / "z.py").write_text("import a.x\n")
    graph = {n: _load_time_imports(n, tmp_path / f"{n[2:]}.py", known) for n in known}
    assert graph == {"a.x": {"a.y"}, "a.y": {"a.z"}, "a.z": {"a.x"}}
    assert find_cycles(graph) == [["a.x", "a.y", "a.z", "a.x"]]


def test_the_checker_sees_a_function_level_circle(tmp_path) -> None:
    """Control: a synthetic package whose modules import each other only inside functions
    (and one relative import in a method) has a circle the function-level graph finds and
    the load-time graph does not."""
    pkg = tmp_path / "p"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "a.py").write_text("import os\n\ndef f():\n    from .sub.b import g\n    return g()\n")
    (pkg / "sub" / "b.py").write_text("class B:\n    def m(self):\n        from ..a import f\n        return f\n"
                                      "def g():\n    return 1\n")
    mods = {"p": pkg / "__init__.py", "p.sub": pkg / "sub" / "__init__.py", "p.a": pkg / "a.py",
            "p.sub.b": pkg / "sub" / "b.py"}
    graph = {n: _load_time_imports(n, path, set(mods), anywhere=True) for n, path in mods.items()}
    assert graph["p.a"] == {"p.sub.b"} and graph["p.sub.b"] == {"p.a"}
    assert find_cycles(graph) == [["p.a", "p.sub.b", "p.a"]]
    assert find_cycles({n: _load_time_imports(n, path, set(mods)) for n, path in mods.items()}) == []


def _imports_anywhere(path: Path, package: str) -> set[str]:
    """Every module a file names in an import, at load time or inside a function."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = package.split(".")[:len(package.split(".")) - (node.level - 1)] if node.level else []
            mod = ".".join(base + ([node.module] if node.module else []))
            found |= {mod} if node.module else {f"{mod}.{a.name}" for a in node.names}
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
    return found


def _learning_upward(root: Path) -> list[tuple[str, str]]:
    out = []
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root).with_suffix("").parts
        if parts[0] == "__init__":
            continue
        package = ".".join(["learning", *parts[:-1]])
        for mod in _imports_anywhere(path, package):
            target = mod.split(".")
            if target[0] == "learning" and len(target) > 1 and \
                    LEARNING.get(target[1], -1) > LEARNING[parts[0]]:
                out.append((".".join(parts), mod))
    return out


def test_learning_sub_packages_point_one_way() -> None:
    """data <- inputs <- models <- evaluation <- training, even in imports inside functions."""
    rooms = [p.stem for p in (ROOT / "learning").iterdir()
             if (p.suffix == ".py" and p.stem != "__init__") or (p / "__init__.py").is_file()]
    assert sorted(rooms) == sorted(LEARNING)
    assert _learning_upward(ROOT / "learning") == []


def test_the_checker_sees_an_upward_import(tmp_path) -> None:
    """Control: a data module that imports from training, inside a function, is found."""
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "x.py").write_text("def f():\n    from ..training.train import g\n")
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "y.py").write_text("from ..inputs.table import t\nfrom learning.data import x\n")
    assert _learning_upward(tmp_path) == [("data.x", "learning.training.train")]


def benchmark_imports(root: Path = ROOT) -> list[tuple[str, str]]:
    """(file, module) for every import statement under root/service, anywhere in a file, that
    names the benchmarks, and for every string constant naming them as a module that is not
    the `bench` command's one constant (`importlib.import_module` would hide behind one)."""
    found = []
    for path in sorted((root / "service").rglob("*.py")):
        rel = path.relative_to(root)
        package = ".".join(rel.parent.parts)
        for mod in _imports_anywhere(path, package):
            if mod.split(".")[0] == BENCHMARKS:
                found.append((str(rel), mod))
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and \
                    node.value.split(".")[0] == BENCHMARKS and (rel.parts[-2:], node.value) != DOOR:
                found.append((str(rel), repr(node.value)))
    return found


#: the one mention of the benchmarks in the service: `noisestop bench` loads them from a checkout
DOOR = (("commands", "bench.py"), BENCHMARKS)


def test_the_service_never_imports_the_benchmarks() -> None:
    """benchmarks/ is outside the installed packages: nothing under service/ imports it, at
    load time or in a function; `noisestop bench` names the folder once and loads it only
    from a source checkout (tests/cli/test_bench_door.py)."""
    assert not (ROOT / "service" / "lab").exists()
    assert len(list((ROOT / "service").rglob("*.py"))) >= 17
    assert benchmark_imports() == []
    door = ROOT / "service" / "commands" / "bench.py"
    constants = [n.value for n in ast.walk(ast.parse(door.read_text()))
                 if isinstance(n, ast.Constant) and isinstance(n.value, str)]
    assert constants.count(BENCHMARKS) == 1


def test_the_checker_sees_the_service_import_the_benchmarks(tmp_path) -> None:
    """Control: a service module importing the benchmarks inside a function, relatively
    from the top, or naming them in a string for importlib is found; the door is not."""
    (tmp_path / "service" / "commands").mkdir(parents=True)
    (tmp_path / "service" / "app.py").write_text("def f():\n    from benchmarks.loadtest import run_load\n")
    (tmp_path / "service" / "oip.py").write_text("import importlib\nm = importlib.import_module('benchmarks.attack')\n")
    (tmp_path / "service" / "commands" / "bench.py").write_text("BENCHMARKS = 'benchmarks'\n")
    (tmp_path / "service" / "registry.py").write_text("import json\n")
    assert benchmark_imports(tmp_path) == [("service/app.py", "benchmarks.loadtest"),
                                           ("service/oip.py", "'benchmarks.attack'")]


def renderer_room_breaches(graph: dict[str, set[str]]) -> list[tuple[str, str]]:
    """(importer, imported) for every import of a renderer module that its room may not make
    (RENDERER_JOBS: the live loop imports neither the simulation nor dataset building, say)."""
    def room(mod: str) -> str | None:
        parts = mod.split(".")
        return parts[1] if parts[0] == "renderer" and len(parts) > 1 else None
    out = []
    for a, deps in graph.items():
        ra = room(a)
        if ra is None or ra in RENDERER_DOORS:
            continue
        allowed = RENDERER_JOBS.get(ra, {"criteria"}) | RENDERER_SHARED | {ra}
        out += [(a, b) for b in deps if b.split(".")[0] == "renderer" and (room(b) not in allowed)]
    return sorted(out)


def test_renderer_jobs_point_one_way() -> None:
    """Each of renderer's five jobs has its folder, and its imports, even inside functions,
    follow RENDERER_JOBS."""
    rooms = {p.stem for p in (ROOT / "renderer").iterdir() if p.suffix == ".py" or (p / "__init__.py").is_file()}
    assert set(RENDERER_JOBS) | RENDERER_SHARED | RENDERER_DOORS | {"__init__"} == rooms
    assert renderer_room_breaches(_graph(anywhere=True)) == []


def test_the_checker_sees_a_job_import_another(tmp_path) -> None:
    """Control: the live loop importing the simulation inside a function, the scene library
    importing the live loop and a shared module importing a job are found; the simulation
    importing the live loop and a door importing anything are not."""
    for pkg in ("renderer", "renderer/live", "renderer/scenes", "renderer/simulation"):
        (tmp_path / pkg).mkdir()
        (tmp_path / pkg / "__init__.py").write_text("")
    (tmp_path / "renderer" / "live" / "adaptive.py").write_text("def f():\n    from ..simulation import simulate\n")
    (tmp_path / "renderer" / "scenes" / "catalog.py").write_text("from renderer.live.adaptive import f\n")
    (tmp_path / "renderer" / "simulation" / "simulate.py").write_text("from ..live import adaptive\n")
    (tmp_path / "renderer" / "spec.py").write_text("from .scenes import catalog\n")
    (tmp_path / "renderer" / "api.py").write_text("from .simulation import simulate\nfrom .live import adaptive\n")
    graph = _graph(anywhere=True, root=tmp_path, packages=("renderer",))
    assert renderer_room_breaches(graph) == [
        ("renderer.live.adaptive", "renderer.simulation"), ("renderer.live.adaptive", "renderer.simulation.simulate"),
        ("renderer.scenes.catalog", "renderer.live.adaptive"), ("renderer.spec", "renderer.scenes"),
        ("renderer.spec", "renderer.scenes.catalog")]
