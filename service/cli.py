"""The `noisestop` command line (DESIGN.md "Command line").

Logs and progress go to stderr; with --json, stdout carries one JSON object and nothing
else. Bad input ends with a one-line error and exit status 2, never a traceback (set
NOISESTOP_DEBUG=1 to see one).
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from collections.abc import Callable, Sequence
from typing import Any

log = logging.getLogger("noisestop")

Handler = Callable[[argparse.Namespace], int]


class UsageError(ValueError):
    """A problem with what the user asked for: reported in one line, exit status 2."""


def emit_json(obj: Any) -> None:
    """The only thing a --json command writes to stdout."""
    sys.stdout.write(json.dumps(obj, indent=None, default=_json_default) + "\n")
    sys.stdout.flush()


def _json_default(o: Any) -> Any:
    import numpy as np
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if hasattr(o, "__fspath__"):
        return os.fspath(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def build_parser() -> argparse.ArgumentParser:
    from . import commands
    parser = argparse.ArgumentParser(
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


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_logging(args.verbose, args.quiet)
    debug = os.environ.get("NOISESTOP_DEBUG") == "1"
    try:
        return int(args.handler(args) or 0)
    except KeyboardInterrupt:
        print("noisestop: interrupted", file=sys.stderr)
        return 130
    except (UsageError, ValueError, FileNotFoundError, NotADirectoryError, PermissionError) as exc:
        if debug:
            raise
        print(f"noisestop {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
