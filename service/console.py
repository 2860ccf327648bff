"""What every `noisestop` command shares with the command line's entry point: the usage
error type, the --json output, the logger and the one-line error text (a module of its own
so that `service.cli` imports `service.commands` and not the other way round)."""
from __future__ import annotations

import json
import logging
import os
import sys
from typing import Any

from noisefeat.jsonout import json_default

log = logging.getLogger("noisestop")


class UsageError(ValueError):
    """A problem with what the user asked for: reported in one line, exit status 2."""


def emit_json(obj: Any) -> None:
    """The only thing a --json command writes to stdout."""
    sys.stdout.write(json.dumps(obj, indent=None, default=json_default) + "\n")
    sys.stdout.flush()


def one_line(exc: BaseException, limit: int = 2000) -> str:
    """An exception's message on one line (Mitsuba's parser errors span several)."""
    if isinstance(exc, MemoryError):
        return "out of memory" + (f" ({exc})" if str(exc) else "")
    if isinstance(exc, RecursionError):
        return f"input nested too deeply ({exc})"
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= limit else text[:limit] + "..."
