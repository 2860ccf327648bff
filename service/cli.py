"""The `noisestop` command line (DESIGN.md "Command line").

Logs and progress go to stderr; with --json, stdout carries one JSON object and nothing
else. Every failure of a command ends with one line on stderr, `noisestop CMD: error:
...`, and exit status 2, never a traceback (set NOISESTOP_DEBUG=1 to see one): bad input
and unusable files say what is wrong with them, a missing optional package names the extra
that installs it (`pip install 'noisestop[render]'`); anything else is reported as an
unexpected error with its type, which is a bug to report (a contract:
tests/cli/test_error_contract.py holds every command to it).
"""
from __future__ import annotations

import argparse
import gc
import logging
import os
import sys
from collections.abc import Callable, Sequence
from typing import NoReturn

from .console import UsageError, emit_json, log, one_line

__all__ = ["main", "run", "build_parser", "UsageError", "emit_json", "log", "one_line"]

Handler = Callable[[argparse.Namespace], int]


class _OneLineParser(argparse.ArgumentParser):
    """argparse's usage errors as one line too (it prints the whole usage block first)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())} (--help for usage)\n")


def build_parser() -> argparse.ArgumentParser:
    from . import commands
    parser = _OneLineParser(
        prog="noisestop", description="Perceptual stopping for Monte Carlo path tracing.")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (stderr)")
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    commands.register(sub)
    return parser


def _setup_logging(verbose: int, quiet: bool) -> None:
    level = logging.WARNING if quiet else (logging.DEBUG if verbose > 0 else logging.INFO)
    logging.basicConfig(level=level, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", datefmt="%H:%M:%S")


def run() -> NoReturn:
    """The `noisestop` executable: `main`, then exit without the final garbage collection.

    Why: at exit CPython collects every object the imports made, and torch's alone take
    about 0.45 s of it on this project's CI machine; frozen (`gc.freeze`), they are left to
    the operating system (0.13 s). Atexit handlers still run. What a user times is the
    whole command. In-process callers (tests) call `main`, which freezes nothing.
    """
    rc = main()
    gc.freeze()
    sys.exit(rc)


def main(argv: Sequence[str] | None = None) -> int:
    if "serve" in (sys.argv[1:] if argv is None else list(argv)):
        from .startup import guard_start_up
        guard_start_up()         # before the imports: a hang-up while serve starts is logged
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_logging(args.verbose, args.quiet)
    debug = os.environ.get("NOISESTOP_DEBUG") == "1"
    try:
        return int(args.handler(args) or 0)
    except KeyboardInterrupt as exc:
        _close_progress_bars()
        print(f"noisestop: interrupted{': ' + one_line(exc) if str(exc) else ''}", file=sys.stderr)
        return 130
    except (UsageError, ValueError, OSError, RecursionError, MemoryError) as exc:
        if debug:
            raise
        _close_progress_bars()
        print(f"noisestop {args.command}: error: {one_line(exc)}", file=sys.stderr)
        return 2
    except Exception as exc:   # a bug: still one line, with what it was
        if debug:
            raise
        _close_progress_bars()
        missing = _missing_extra(exc)
        if missing is not None:   # an optional package not installed: which extra brings it
            print(f"noisestop {args.command}: error: {one_line(missing)}", file=sys.stderr)
            return 2
        print(f"noisestop {args.command}: error: unexpected {type(exc).__name__}: {one_line(exc)} "
              "(a bug; NOISESTOP_DEBUG=1 shows where)", file=sys.stderr)
        return 2


def _missing_extra(exc: BaseException) -> ImportError | None:
    """`exc` as the one-line MissingExtra if it says an optional package is not installed."""
    if not isinstance(exc, ImportError):
        return None
    from noisefeat.extras import missing_extra
    return missing_extra(exc)


def _close_progress_bars() -> None:
    """A bar interrupted by the error would share its line; closed, it clears itself."""
    tqdm = sys.modules.get("tqdm")
    for bar in list(getattr(getattr(tqdm, "tqdm", None), "_instances", ()) or ()):
        try:
            bar.close()
        except Exception:   # a bar in a bad state must not hide the error line
            pass


if __name__ == "__main__":
    sys.exit(main())
