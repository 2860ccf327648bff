"""The house rules, checked on the source: dependencies point one way (noisefeat <-
learning <- renderer <- service, DESIGN.md, and inside learning its sub-packages in the
order of their jobs), and no modules import each other around a circle, neither at load
time nor through imports inside functions (a function-level import only hides a circle
until the function runs)."""
from __future__ import annotations

import ast
from pathlib import Path
from tests.support import ROOT

PACKAGES = ("noisefeat", "learning", "renderer", "service")
#: learning's rooms, each importing only from those before it (learning/__init__.py)
LEARNING = {"names": 0, "stoprule": 0, "data": 1, "inputs": 2, "models": 3, "evaluation": 4, "training": 5}


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for path in (ROOT / pkg).rglob("*.py"):
            rel = path.relative_to(ROOT).with_suffix("")
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


def _graph(anywhere: bool = False) -> dict[str, set[str]]:
    mods = _modules()
    known = set(mods)
    return {name: _load_time_imports(name, path, known, anywhere) for name, path in mods.items()}


def test_dependencies_point_one_way() -> None:
    rank = {pkg: i for i, pkg in enumerate(PACKAGES)}
    upward = [(a, b) for a, deps in _graph().items() for b in deps
              if rank[b.split(".")[0]] > rank[a.split(".")[0]]]
    assert upward == []


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


def test_the_service_never_imports_the_lab() -> None:
    """service/lab is the benchmark lab; of the service's rooms only the `bench` command
    opens its door."""
    rooms = [p for p in (ROOT / "service").rglob("*.py")
             if "lab" not in p.relative_to(ROOT).parts and p.relative_to(ROOT).parts[-2:] != ("commands", "bench.py")]
    assert len(rooms) >= 16

    def package(p: Path) -> str:
        return ".".join(p.relative_to(ROOT).parent.parts)
    found = [(p.stem, m) for p in rooms for m in _imports_anywhere(p, package(p)) if m.startswith("service.lab")]
    assert found == []
    door = ROOT / "service" / "commands" / "bench.py"
    assert any(m.startswith("service.lab") for m in _imports_anywhere(door, package(door)))
