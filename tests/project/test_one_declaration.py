"""One declaration per setting: no module of `renderer` checks or defaults a
render setting outside its declaration, the render spec's row (`renderer/settings.py`,
checked and combined once by `renderer/spec.py`) or a criterion's own declaration (its
`settings`, read through the same rows).

What counts, found by walking each module's syntax tree (a setting is a row's name):

* a row's check or parse called outside the table (``ROW["tau"].check(x)``);
* a parameter named after a setting with a default other than None or the row's own
  (``tau: float = 0.02``, ``tau=DEFAULT_TAU``; ``ROW["tau"].default`` reads the declaration);
* a setting defaulted inline: ``tau or DEFAULT_TAU``, ``tau if tau is not None else 0.02``,
  ``settings.get("seed", 0)``;
* a class field named after a setting with a literal default (a dataclass's).

`ALLOWED` names each exception with its reason; an exception that no longer occurs fails
too, so the list cannot go stale. A control plants one of each in a scratch package.
"""
from __future__ import annotations

import ast
from pathlib import Path
from typing import NamedTuple

from renderer.settings import ROWS
from tests.support import ROOT

SETTINGS = frozenset(r.name for r in ROWS)
#: the declarations themselves: the rows (each checking its values), and the one resolver
DECLARATIONS = frozenset({"renderer/settings.py", "renderer/spec.py"})
_DISPLAY = "the display transform's exposure (DESIGN 'Display transform', default 0), for images outside a render too"
_SIMULATE = ("the offline simulation's own door (stored stacks, evaluate): it takes its settings directly, not "
             "through resolve")
#: (module, scope, setting) -> why it may stay
ALLOWED: dict[tuple[str, str, str], str] = {
    ("renderer/live/blocks.py", "BlockRenderer.quick_image", "seed"):
        "a method's own default for callers outside a render (the loop and the dataset build pass theirs)",
    ("renderer/scenes/heldout.py", "marble", "seed"): "a procedural texture's seed, not the sampler's",
    ("renderer/scenes/heldout.py", "wood", "seed"): "a procedural texture's seed, not the sampler's",
    ("renderer/scenes/heldout.py", "studio_environment", "seed"): "a procedural texture's seed, not the sampler's",
    ("renderer/live/outputs.py", "to_srgb8", "exposure"): _DISPLAY,
    ("renderer/live/report.py", "window_dots", "exposure"): _DISPLAY,
    ("renderer/live/report.py", "final_vs_reference", "exposure"): _DISPLAY,
    ("renderer/plugin.py", "NoisestopIntegrator.render", "seed"):
        "Mitsuba's Integrator.render signature (mi.render's seed, added to the resolved one)",
    ("renderer/live/passloop.py", "PassLoop.__init__", "decide_skip"):
        "the loop's own default for callers outside a render (every pass judged); a render passes its spec's",
    ("renderer/live/passloop.py", "PassLoop.__init__", "decide_growth"):
        "the loop's own default for callers outside a render (every pass judged); a render passes its spec's",
    ("renderer/client/remote.py", "RemoteModel.__init__", "model"):
        "the name a verdict server serves a model under (DESIGN 'HTTP API': `default`), not a bundle's path",
    ("renderer/simulation/simulate.py", "_as_stacks", "tau"): _SIMULATE,
    ("renderer/simulation/simulate.py", "evaluate_criterion", "tau"): _SIMULATE,
    ("renderer/simulation/simulate.py", "evaluate_criterion_cli", "tau"): _SIMULATE,
    ("renderer/simulation/simulate.py", "criterion_factory", "tile"): _SIMULATE + " (None: whole blocks)",
    **{("renderer/dataset/stackbuild.py", "BuildSettings", name):
       "the dataset build's own settings (its one table, stored in each stack's meta.json), not a render's"
       for name in ("resolution", "step", "grid", "quick_spp", "seed")},
}


class Finding(NamedTuple):
    module: str
    scope: str
    setting: str
    what: str
    line: int


def _name(node: ast.AST) -> str | None:
    return node.id if isinstance(node, ast.Name) else node.attr if isinstance(node, ast.Attribute) else None


def _literal(node: ast.AST | None) -> bool:
    """A default written out: a constant other than None, an ALL_CAPS name, a tuple, -1."""
    if isinstance(node, ast.Constant):
        return node.value is not None and node.value is not Ellipsis      # `...`: a stub's
    if isinstance(node, ast.Name):
        return node.id.isupper()
    return isinstance(node, (ast.Tuple, ast.List, ast.UnaryOp))


def _findings(tree: ast.AST, module: str) -> list[Finding]:
    out: list[Finding] = []

    def visit(node: ast.AST, scope: list[str]) -> None:
        here = ".".join(scope) or "<module>"

        def found(setting: str, what: str) -> None:
            out.append(Finding(module, here, setting, what, getattr(node, "lineno", 0)))

        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) \
                and node.func.attr in ("check", "parse") and isinstance(node.func.value, ast.Subscript) \
                and _name(node.func.value.value) == "ROW" and isinstance(node.func.value.slice, ast.Constant):
            found(node.func.value.slice.value, "a row's check outside the table")
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) \
                and node.func.attr in ("get", "pop", "setdefault") and len(node.args) == 2 \
                and isinstance(node.args[0], ast.Constant) and node.args[0].value in SETTINGS \
                and _literal(node.args[1]):
            found(node.args[0].value, f"defaulted inline: {ast.unparse(node)}")
        if isinstance(node, ast.BoolOp) and isinstance(node.op, ast.Or) and _name(node.values[0]) in SETTINGS \
                and any(_literal(v) for v in node.values[1:]):
            found(_name(node.values[0]), f"defaulted inline: {ast.unparse(node)}")   # type: ignore[arg-type]
        if isinstance(node, ast.IfExp) and isinstance(node.test, ast.Compare) and len(node.test.ops) == 1 \
                and isinstance(node.test.ops[0], (ast.Is, ast.IsNot)) \
                and isinstance(node.test.comparators[0], ast.Constant) and node.test.comparators[0].value is None:
            tested = ast.unparse(node.test.left)
            kept, other = (node.orelse, node.body) if isinstance(node.test.ops[0], ast.Is) else (node.body, node.orelse)
            if _name(node.test.left) in SETTINGS and ast.unparse(kept) == tested and _literal(other):
                found(_name(node.test.left), f"defaulted inline: {ast.unparse(node)}")   # type: ignore[arg-type]
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            a = node.args
            positional = a.posonlyargs + a.args
            pairs = list(zip(positional[len(positional) - len(a.defaults):], a.defaults)) + \
                list(zip(a.kwonlyargs, a.kw_defaults))
            where = ".".join([*scope, node.name]) if not isinstance(node, ast.Lambda) else here
            for arg, default in pairs:
                if arg.arg in SETTINGS and _literal(default):
                    out.append(Finding(module, where, arg.arg, f"parameter default {arg.arg}={ast.unparse(default)}",
                                       node.lineno))   # type: ignore[arg-type]
        if isinstance(node, ast.ClassDef):
            for st in node.body:
                if isinstance(st, ast.AnnAssign) and isinstance(st.target, ast.Name) and st.target.id in SETTINGS \
                        and _literal(st.value):
                    out.append(Finding(module, ".".join([*scope, node.name]), st.target.id,
                                       f"field default {st.target.id} = {ast.unparse(st.value)}", st.lineno))  # type: ignore[arg-type]
        inner = [*scope, node.name] if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) \
            else scope
        for child in ast.iter_child_nodes(node):
            visit(child, inner)

    visit(tree, [])
    return out


def offenders(root: Path, package: str = "renderer", skip: frozenset[str] = DECLARATIONS) -> list[Finding]:
    """Every check or default of a setting outside its declaration in `package` under `root`."""
    found = []
    for path in sorted((root / package).rglob("*.py")):
        module = path.relative_to(root).as_posix()
        if module not in skip:
            found += _findings(ast.parse(path.read_text()), module)
    return found


def test_no_setting_is_checked_or_defaulted_outside_its_declaration() -> None:
    found = offenders(ROOT)
    unexplained = [f for f in found if (f.module, f.scope, f.setting) not in ALLOWED]
    assert unexplained == [], "\n".join(f"{f.module}:{f.line} {f.scope}: {f.what}" for f in unexplained)
    stale = set(ALLOWED) - {(f.module, f.scope, f.setting) for f in found}
    assert stale == set(), f"allowed but no longer there: {sorted(stale)}"


def test_the_checker_sees_each_kind_of_offender(tmp_path: Path) -> None:
    """Control: one offender of each kind, planted in a scratch package, is found; the same
    settings read from their declaration are not."""
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "bad.py").write_text(
        "from dataclasses import dataclass\n"
        "def f(tau=0.02, *, exposure=DEFAULT_EXPOSURE):\n"
        "    x = ROW['threshold'].check(tau)\n"
        "    return settings.get('seed', 0), spec.offset or 0.5, q if q is not None else 1.0\n"
        "class C:\n"
        "    def m(self, quantile=None):\n"
        "        return quantile if quantile is not None else 1.0\n"
        "@dataclass\n"
        "class S:\n"
        "    step: int = 16\n")
    (tmp_path / "pkg" / "good.py").write_text(
        "def f(tau=ROW['tau'].default, seed=None, sides=2):\n"
        "    return ROW['tau'].doc, values.get('seed'), 'block' if tile is None else 'tile'\n")
    found = {(f.module, f.scope, f.setting) for f in offenders(tmp_path, "pkg", frozenset())}
    assert found == {("pkg/bad.py", "f", s) for s in ("tau", "exposure", "threshold", "seed", "offset")} | {
        ("pkg/bad.py", "C.m", "quantile"), ("pkg/bad.py", "S", "step")}
