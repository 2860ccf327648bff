"""mkdocs hooks for `make docs` (mkdocs.yml `hooks`): the README is the site's home page and
BENCHMARKS.md its benchmarks report, read from the top of the repository where they live, and
every relative link is rewritten from its place in the repository to its place in the site.

Why: the Markdown files link to each other as the repository lays them out (README.md to
docs/guide/rendering.md, a guide to ../../BENCHMARKS.md), which is what a reader of the
repository follows; in the site the same files sit elsewhere. A link to a file the site does
not hold (a source file, benchmarks/realscenes/SOURCES.md) keeps its text and loses its link.
"""
from __future__ import annotations

import posixpath
import re
from pathlib import Path
from typing import Any

from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parent.parent
#: repository files shown as pages: repository path -> path in the site's docs
PAGES = {"README.md": "index.md", "BENCHMARKS.md": "benchmarks/index.md"}
#: a Markdown link or image: [text](target) or ![alt](target)
LINK = re.compile(r"(?P<head>!?\[(?P<text>[^\]]*)\]\()(?P<target>[^)\s]+)\)")
EXTERNAL = re.compile(r"^([a-z][a-z0-9+.-]*:|#|/)", re.IGNORECASE)


def on_files(files: Files, config: Any) -> Files:
    for source, uri in PAGES.items():
        files.append(File.generated(config, uri, abs_src_path=str(ROOT / source)))
    return files


def repository_path(uri: str) -> str:
    """Where the page at `uri` (in the site's docs) lives in the repository."""
    return {page: source for source, page in PAGES.items()}.get(uri, f"docs/{uri}")


def site_link(target: str, page_uri: str) -> str | None:
    """`target`, a link relative to the page's place in the repository, relative to its place
    in the site; None for a file the site does not hold."""
    if EXTERNAL.match(target):
        return target
    path, _, anchor = target.partition("#")
    here = posixpath.dirname(repository_path(page_uri))
    repo = posixpath.normpath(posixpath.join(here, path))
    if repo in PAGES:
        uri = PAGES[repo]
    elif repo.startswith("docs/"):
        uri = repo[len("docs/"):]
    else:
        return None
    link = posixpath.relpath(uri, posixpath.dirname(page_uri) or ".")
    return link + (f"#{anchor}" if anchor else "")


def on_page_markdown(markdown: str, page: Any, config: Any, files: Files) -> str:
    def fix(m: re.Match[str]) -> str:
        link = site_link(m.group("target"), page.file.src_uri)
        return m.group("text") if link is None else f"{m.group('head')}{link})"
    return LINK.sub(fix, markdown)
