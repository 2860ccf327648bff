"""Input files that are no regular files, as a hostile user or a broken disk makes them:
shared by the tests and the hardening bench."""
from __future__ import annotations

import os
from pathlib import Path

#: the kinds `bad_file` makes
BAD_KINDS = ("/dev/zero", "FIFO", "3 GB sparse", "missing")


def bad_file(path: Path, kind: str) -> Path:
    """`path` made into a file of `kind` (`BAD_KINDS`): a link to /dev/zero, a FIFO, a 3 GB
    sparse file (no disk used), or nothing at all."""
    if kind == "/dev/zero":
        path.symlink_to("/dev/zero")
    elif kind == "FIFO":
        os.mkfifo(path)
    elif kind == "3 GB sparse":
        with open(path, "wb") as f:
            f.truncate(3 << 30)
    elif kind != "missing":
        raise ValueError(f"unknown kind {kind!r}; known: {', '.join(BAD_KINDS)}")
    return path
