"""The marked sections of BENCHMARKS.md: each bench rewrites only the text between its markers.

Why a module of its own: `bench` (every section), `bench_native` and `bench_cost` (run on
their own, on a GPU machine too) all write their figures this way; with the helper here
the imports point one way (bench -> bench_native -> marked_sections), with no circle.
"""
from __future__ import annotations

import os
from pathlib import Path

from noisefeat.atomic import atomic_write
from noisefeat.safeio import InputFileError, read_text


def check_target(path: Path) -> str:
    """The text of the markdown file `path` ('' if it does not exist yet), or one line
    (InputFileError) saying why it cannot be rewritten: a device, a FIFO, a folder, a file
    over the cap or not UTF-8, or a folder that is missing or not writable. `bench --update`
    calls it before measuring, so a bad FILE costs no benchmark run."""
    text = read_text(path, "markdown") if os.path.lexists(path) else ""
    folder = path.parent
    if not folder.is_dir():
        raise InputFileError(f"{path}: its folder {folder} does not exist")
    if not os.access(folder, os.W_OK):
        raise InputFileError(f"{path}: its folder {folder} is not writable (the file is rewritten beside it)")
    return text


def update_markdown(path: Path, sections: dict[str, str]) -> None:
    """Replace the text between <!-- bench:NAME --> and <!-- /bench:NAME --> markers."""
    text = check_target(path)
    for name, body in sections.items():
        start, end = f"<!-- bench:{name} -->", f"<!-- /bench:{name} -->"
        block = f"{start}\n{body}\n{end}"
        if start in text and end in text:
            i, j = text.index(start), text.index(end) + len(end)
            text = text[:i] + block + text[j:]
        else:
            text += f"\n{block}\n"
    atomic_write(path, text)
