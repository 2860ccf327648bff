"""DESIGN's Python API names document every parameter (numpy style) and what they return.

The "Parameters" section is read as numpydoc lays it out: a heading underlined with dashes,
then entries `name : type` (or a bare `name`, or `a, b : type`) at the section's own
indentation, each followed by its description indented deeper; the section ends at the
next underlined heading. So a description line that happens to start with a word and a
colon ("Seconds: ...") is description, not a parameter.
"""
from __future__ import annotations

import inspect
import re

import pytest

import learning
import noisefeat
import renderer

API = {
    "noisefeat.split_blocks": noisefeat.split_blocks,
    "noisefeat.extract_features": noisefeat.extract_features,
    "noisefeat.FeatureBase": noisefeat.FeatureBase,
    "noisefeat.FeatureBase.forward": noisefeat.FeatureBase.forward,
    "learning.read_stack": learning.read_stack,
    "learning.write_stack": learning.write_stack,
    "learning.load_model": learning.load_model,
    "renderer.render": renderer.render,
}

_NAME = re.compile(r"\*{0,2}[A-Za-z_]\w*")


def sections(doc: str) -> dict[str, list[str]]:
    """Heading -> its lines, for every heading underlined by dashes of at least its length."""
    lines = doc.expandtabs().splitlines()
    out: dict[str, list[str]] = {}
    current: list[str] | None = None
    i = 0
    while i < len(lines):
        title, under = lines[i].strip(), lines[i + 1].strip() if i + 1 < len(lines) else ""
        if title and under and set(under) == {"-"} and len(under) >= len(title):
            current = out.setdefault(title, [])
            i += 2
            continue
        if current is not None:
            current.append(lines[i])
        i += 1
    return out


def documented(doc: str) -> dict[str, str]:
    """Parameter name -> its description, from the "Parameters" section (none: {})."""
    body = sections(doc).get("Parameters", [])
    filled = [line for line in body if line.strip()]
    if not filled:
        return {}
    base = min(len(line) - len(line.lstrip()) for line in filled)
    out: dict[str, str] = {}
    names: list[str] = []
    for line in filled:
        indent = len(line) - len(line.lstrip())
        if indent == base:                                   # an entry: `name : type` or `name`
            spec = line.strip().split(" : ", 1)[0].rstrip(":").strip()
            names = [n.strip().lstrip("*") for n in spec.split(",")]
            if not all(_NAME.fullmatch(n) for n in names):
                raise ValueError(f"not a parameter entry: {line.strip()!r}")
            out.update({n: "" for n in names})
        elif names:                                          # its description
            for n in names:
                out[n] = (out[n] + " " + line.strip()).strip()
    return out


def check(obj: object) -> list[str]:
    """What is wrong with the docstring of `obj`: parameters it does not document, entries
    that are not parameters, entries with no description, a missing Returns section."""
    doc = inspect.getdoc(obj) or ""
    problems = []
    if "Parameters" not in sections(doc):
        problems.append("no Parameters section")
    if ("Returns" in sections(doc)) == inspect.isclass(obj):          # classes: Attributes instead
        problems.append("Returns section" + (" on a class" if inspect.isclass(obj) else " missing"))
    params = [p for p in inspect.signature(obj).parameters if p != "self"]
    docs = documented(doc)
    problems += [f"undocumented parameter {p}" for p in params if p not in docs]
    problems += [f"documented but not a parameter: {d}" for d in docs if d not in params]
    problems += [f"no description: {d}" for d, text in docs.items() if not text]
    return problems


@pytest.mark.parametrize("name", sorted(API))
def test_every_parameter_is_documented(name: str) -> None:
    assert check(API[name]) == [], name


def test_the_render_docstring_is_read_entry_by_entry() -> None:
    """renderer.render's entries are exactly its parameters, in order; its description
    lines that begin "Seconds:" or "None:" are description."""
    doc = inspect.getdoc(renderer.render) or ""
    assert list(documented(doc)) == list(inspect.signature(renderer.render).parameters)
    assert "Seconds" not in documented(doc) and "None" not in documented(doc)
    assert documented(doc)["time_limit"].startswith("Seconds: the pass under way")


def _without(doc: str, name: str, mention: bool) -> str:
    """`doc` with parameter `name`'s entry and description cut out; with `mention`, a line
    "name: ..." left in the description before it (which a "Word:" reading took for one)."""
    lines = doc.splitlines()
    start = next(i for i, line in enumerate(lines) if re.match(rf"{name}( :|$)", line))
    end = next(i for i in range(start + 1, len(lines)) if lines[i] and not lines[i][0].isspace())
    return "\n".join(lines[:start] + ([f"    {name}: mentioned in a description"] if mention else []) + lines[end:])


@pytest.mark.parametrize("mention", [False, True], ids=["cut", "mentioned"])
@pytest.mark.parametrize("missing", ["time_limit", "seed", "spp_budget"])
def test_the_checker_sees_a_render_parameter_missing(missing: str, mention: bool) -> None:
    """Control: renderer.render with one entry cut from its docstring fails the check, also
    where a description line still begins with the name and a colon."""
    def broken(*args, **kwargs):
        return renderer.render(*args, **kwargs)

    broken.__signature__ = inspect.signature(renderer.render)
    broken.__doc__ = _without(inspect.getdoc(renderer.render) or "", missing, mention)
    assert missing not in documented(broken.__doc__)
    assert check(broken) == [f"undocumented parameter {missing}"]


def test_the_checker_sees_stale_and_empty_entries() -> None:
    """Control: an entry for a parameter that is gone, one without a description and a
    parameter of the signature listed nowhere (only in another section) are all found."""
    def f(a, b, *, c=1):
        """Do f.

        Parameters
        ----------
        a : int
            Seconds: a line that looks like an entry.
        old : str
            A parameter that is gone.
        b

        Returns
        -------
        int
            c : not a parameter entry, in another section.
        """
    assert check(f) == ["undocumented parameter c", "documented but not a parameter: old", "no description: b"]
    with pytest.raises(ValueError, match="not a parameter entry"):
        documented("Parameters\n----------\nthe scene (a sentence) : x\n    y\n")
