"""The marked sections of BENCHMARKS.md: each bench rewrites only the text between its markers.

Why a module of its own: `bench` (every section), `bench_native` and `bench_cost` (run on
their own, on a GPU machine too) all write their figures this way; with the helper here
the imports point one way (bench -> bench_native -> marked_sections), with no circle.
"""
from __future__ import annotations

from pathlib import Path

from noisefeat.atomic import atomic_write


def update_markdown(path: Path, sections: dict[str, str]) -> None:
    """Replace the text between <!-- bench:NAME --> and <!-- /bench:NAME --> markers."""
    text = path.read_text() if path.exists() else ""
    for name, body in sections.items():
        start, end = f"<!-- bench:{name} -->", f"<!-- /bench:{name} -->"
        block = f"{start}\n{body}\n{end}"
        if start in text and end in text:
            i, j = text.index(start), text.index(end) + len(end)
            text = text[:i] + block + text[j:]
        else:
            text += f"\n{block}\n"
    atomic_write(path, text)
