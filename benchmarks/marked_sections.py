"""The marked sections of BENCHMARKS.md: each bench rewrites only the text between its markers.

Why a module of its own: `bench` (every section), `bench_native` and `bench_cost` (run on
their own, on a GPU machine too) all write their figures this way; with the helper here
the imports point one way (bench -> bench_native -> marked_sections), with no circle.

Where a section lives: the report (BENCHMARKS.md) holds the headline and each area's
current figures; the long tables a bench writes (every scene, every setting of a sweep)
live on its detail pages, the Markdown files under `docs/benchmarks/` beside the report,
which the docs site shows. A section is written where its markers are: in the file named,
else on one of its detail pages; a section whose markers are nowhere is appended to the
file named. The benches write links relative to the report (`docs/pareto.png`); on a detail
page they are rebased to the page's folder (`../pareto.png`), so they work from both.
"""
from __future__ import annotations

import os
import re
from pathlib import Path

from noisefeat.atomic import atomic_write
from noisefeat.safeio import InputFileError, read_text

#: where a report's detail pages are, relative to the report's folder
DETAILS = Path("docs") / "benchmarks"
#: a Markdown link or image with its target: [text](target), ![alt](target)
_LINK = re.compile(r"(!?\[[^\]]*\]\()([^)\s]+)\)")
_ABSOLUTE = re.compile(r"^([a-z][a-z0-9+.-]*:|#|/)", re.IGNORECASE)


def rebase_links(body: str, source: Path, target: Path) -> str:
    """`body`'s relative links, written for a file in folder `source`, for one in `target`."""
    def fix(m: re.Match[str]) -> str:
        link = m.group(2)
        if _ABSOLUTE.match(link):
            return m.group(0)
        moved = os.path.relpath(os.path.join(source, link), target)
        return f"{m.group(1)}{Path(moved).as_posix()})"
    return _LINK.sub(fix, body)


def check_target(path: Path) -> str:
    """The text of the markdown file `path` ('' if it does not exist yet), or one line
    (InputFileError) saying why it cannot be rewritten: a device, a FIFO, a folder, a file
    over the cap or not UTF-8, or a folder that is missing or not writable. `bench --update`
    calls it before measuring, so a bad FILE costs no benchmark run. Its detail pages are
    read too, for the same reason."""
    text = read_text(path, "markdown") if os.path.lexists(path) else ""
    folder = path.parent
    if not folder.is_dir():
        raise InputFileError(f"{path}: its folder {folder} does not exist")
    if not os.access(folder, os.W_OK):
        raise InputFileError(f"{path}: its folder {folder} is not writable (the file is rewritten beside it)")
    for page in detail_pages(path):
        read_text(page, "markdown")
    return text


def detail_pages(path: Path) -> list[Path]:
    """The detail pages of the report `path`: the Markdown files under DETAILS beside it."""
    folder = path.parent / DETAILS
    return sorted(folder.glob("*.md")) if folder.is_dir() else []


def _markers(name: str) -> tuple[str, str]:
    return f"<!-- bench:{name} -->", f"<!-- /bench:{name} -->"


def _home(texts: dict[Path, str], report: Path, name: str) -> Path:
    """The file of `texts` (the report first, then its detail pages) that holds section
    `name`'s markers, else the report (where a new section is appended)."""
    start, end = _markers(name)
    return next((f for f, text in texts.items() if start in text and end in text), report)


def update_markdown(path: Path, sections: dict[str, str]) -> None:
    """Replace the text between <!-- bench:NAME --> and <!-- /bench:NAME --> markers, in
    `path` or on the detail page that holds them (a new section: appended to `path`)."""
    texts = {path: check_target(path), **{page: read_text(page, "markdown") for page in detail_pages(path)}}
    by_file: dict[Path, dict[str, str]] = {}
    for name, body in sections.items():
        by_file.setdefault(_home(texts, path, name), {})[name] = body
    for target, its_sections in by_file.items():
        text = texts[target]
        for name, body in its_sections.items():
            if target != path:
                body = rebase_links(body, path.parent, target.parent)
            start, end = _markers(name)
            block = f"{start}\n{body}\n{end}"
            if start in text and end in text:
                i, j = text.index(start), text.index(end) + len(end)
                text = text[:i] + block + text[j:]
            else:
                text += f"\n{block}\n"
        atomic_write(target, text)
