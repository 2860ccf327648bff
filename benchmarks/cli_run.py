"""One `noisestop` command in a fresh process, as a user runs it: exit status, seconds,
stderr lines, its last line and the process's peak RSS.

Why a fresh process: the hostile-file cases (docs/benchmarks/reliability.md) are judged on
what a user sees (one line, exit 2) and on the memory the command took, which only a
process of its own shows.
"""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

#: the checkout: commands run with it on PYTHONPATH, the tests' fixtures are read from it
ROOT = Path(__file__).resolve().parents[1]


def run_cli(argv: list[str], env: dict[str, str] | None = None, timeout: float = 60.0) -> dict[str, Any]:
    """One `noisestop` command: exit status, seconds, stderr lines, last line, peak RSS (KiB)."""
    t0 = time.monotonic()
    environ = {**os.environ, "PYTHONPATH": str(ROOT), **(env or {})}
    environ = {k: v for k, v in environ.items() if k not in ("NOISESTOP_TOKEN",) or "NOISESTOP_TOKEN_FILE" not in (env or {})}
    wrapper = ("import resource, subprocess, sys; r = subprocess.run(sys.argv[1:]); "
               "print('PEAK_RSS_KIB', resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, file=sys.stderr); "
               "sys.exit(r.returncode)")
    proc = subprocess.Popen([sys.executable, "-c", wrapper, sys.executable, "-m", "service.cli", *argv], env=environ, cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        _, err = proc.communicate(timeout=timeout)
        code: int | str = proc.returncode
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        code = "hung"
    peak = [int(x.split()[1]) for x in err.splitlines() if x.startswith("PEAK_RSS_KIB ")]
    lines = [x for x in err.splitlines() if x.strip() and not x.startswith("PEAK_RSS_KIB ")]
    return {"exit": code, "seconds": time.monotonic() - t0, "lines": len(lines),
            "message": lines[-1][:200] if lines else "", "tracebacks": err.count("Traceback"),
            "stderr_nonfinite": sum("non-finite samples:" in x for x in lines),
            "peak_rss_kib": peak[0] if peak else 0}
