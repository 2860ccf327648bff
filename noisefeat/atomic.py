"""Atomic file writes: a reader sees either the old file (or none) or the complete new one.

Every file noisestop writes (dataset levels, model bundles, calibration files, plots,
checkpoints, reports) goes through `atomic_write` or `atomic_path`: the content is written
to a temporary name in the target directory (so the rename stays on one filesystem),
fsync'ed, renamed over the final name with `os.replace`, and the directory is fsync'ed
too. On any error the temporary file is removed and the target is untouched. Temporary
names start with a dot and carry `.tmp` plus the target's suffix (`.plot.png.123.9f1c.tmp.png`),
so writers that pick a format by extension (matplotlib, `np.savez`) keep working and
`noisestop dataset check` recognises leftovers of a killed process.

It lives in `noisefeat`, the lowest package, so that every package may use it.
"""
from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Callable, Iterator
from pathlib import Path

__all__ = ["atomic_path", "atomic_write", "is_temporary", "naming"]


@contextlib.contextmanager
def naming(path: str | os.PathLike) -> Iterator[None]:
    """Give an OSError without a file name (ENOSPC from a write) the name of `path`: the OS
    would otherwise raise "No space left on device" without any file name."""
    try:
        yield
    except OSError as exc:
        if exc.filename is not None:
            raise
        raise type(exc)(exc.errno, exc.strerror or str(exc), str(path)) from None


def temporary_name(path: Path) -> Path:
    """A fresh hidden temporary name next to `path`, keeping its suffix."""
    return path.parent / f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp{path.suffix}"


def is_temporary(name: str) -> bool:
    """Whether a file name is one `atomic_path` makes (a leftover when nobody is writing)."""
    return name.startswith(".") and (name.endswith(".tmp") or ".tmp." in name)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path to write; on a clean exit it replaces `path` atomically.

    The parent directory is created if needed. The caller writes the whole file to the
    yielded path (by any library); it is then fsync'ed and renamed over `path`. If the
    block raises, the temporary file is removed and `path` is left as it was.

    Parameters
    ----------
    path : str or os.PathLike
        The final file name.

    Yields
    ------
    pathlib.Path
        The temporary file to write, in the same directory as `path`.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_name(path)
    try:
        with naming(path):
            yield tmp
            _fsync_file(tmp)
            os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)


def atomic_write(path: str | os.PathLike, data: bytes | str | Callable[[Path], object]) -> Path:
    """Write `data` to `path` atomically (see `atomic_path`).

    Parameters
    ----------
    path : str or os.PathLike
        The final file name.
    data : bytes, str or callable
        The content: bytes as they are, str encoded as UTF-8, or a function called with the
        temporary path that writes the file itself (e.g. ``lambda p: fig.savefig(p)``).

    Returns
    -------
    pathlib.Path
        `path`.
    """
    path = Path(path)
    with atomic_path(path) as tmp:
        if callable(data):
            data(tmp)
        else:
            payload = data.encode("utf-8") if isinstance(data, str) else bytes(data)
            # O_EXCL: never clobber another writer's temp file; mode 0o666 lets the umask decide
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            with os.fdopen(fd, "wb") as f:
                f.write(payload)
    return path


def _fsync_file(path: Path) -> None:
    """Flush the written file to disk before the rename makes it visible."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(directory: Path) -> None:
    """Make the rename durable too (best effort: not every filesystem allows it)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
