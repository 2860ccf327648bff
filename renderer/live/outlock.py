"""One render at a time per output folder (two renders into one folder left final.exr from one and
report.json from the other): an advisory `flock` on out/.noisestop.lock, which the kernel drops when
its holder dies (kill -9 too), so a lock a killed run left is taken over (logged), and one a running
render holds refuses the second render in one line."""
from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import socket
import stat
import time
from collections.abc import Iterator
from pathlib import Path

log = logging.getLogger(__name__)

LOCK_NAME = ".noisestop.lock"


class OutputLocked(ValueError):
    """Another render holds this output folder."""


@contextlib.contextmanager
def locked_output(out: str | os.PathLike) -> Iterator[Path]:
    """Hold the lock of folder `out` (created if missing) while the block runs."""
    from .outputs import prepare_output_dir
    created = not Path(out).exists()
    out = prepare_output_dir(out)     # "", "/", a file, an unwritable folder: their one-line errors first
    path = out / LOCK_NAME
    fd = _open_lock(path)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise OutputLocked(f"{out}: another render is writing into this folder ({_holder(fd)}); wait for it "
                               "to end or choose another --out") from None
        previous = _holder(fd)
        if previous != "unknown process":
            log.warning("%s: taking over the lock left by a render that did not end cleanly (%s)", out, previous)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()}, since {time.strftime('%Y-%m-%d %H:%M:%S')}\n"
                  .encode(), 0)
        try:
            yield out
        finally:
            with contextlib.suppress(OSError):
                os.unlink(path)          # a clean end leaves no lock file behind
                if created:
                    out.rmdir()          # nor a folder it made, if the render wrote nothing
    finally:
        os.close(fd)


def _open_lock(path: Path) -> int:
    """The lock file's descriptor; a link, a FIFO or a device in its place: one line."""
    flags = os.O_RDWR | os.O_CREAT | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_NOFOLLOW", 0)
    try:
        fd = os.open(path, flags, 0o644)
    except OSError as exc:
        what = "a symbolic link" if path.is_symlink() else exc.strerror or str(exc)
        raise ValueError(f"{path}: the output folder's lock file cannot be opened ({what}); remove it "
                         "if no render is running") from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise ValueError(f"{path}: the output folder's lock file is not a regular file; remove it "
                         "if no render is running")
    os.set_blocking(fd, True)
    return fd


def _holder(fd: int) -> str:
    try:
        text = os.pread(fd, 200, 0).decode(errors="replace").strip()
    except OSError:
        text = ""
    return text or "unknown process"
