"""The one error contract's checks, shared by every test of a failing command: a command
runs in process through `service.cli.main` (the console script's code path), and a failure
is exit 2 with exactly one error line on stderr, no traceback."""
from __future__ import annotations

import re

import pytest

from service import cli


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str]:
    """(exit code, stderr) of `noisestop ARGV` run in process."""
    capsys.readouterr()
    try:
        rc = cli.main(list(argv))
    except SystemExit as exc:          # argparse
        rc = exc.code
    return rc, capsys.readouterr().err


def assert_one_line_error(rc: int, err: str, *needles: str) -> None:
    """Exit 2 and one error line; progress bars (tqdm, on stderr by design) aside."""
    lines = [line for line in re.split(r"[\r\n]", err) if line.strip() and "%|" not in line]
    assert rc == 2, (rc, err)
    assert "Traceback" not in err and len(lines) == 1, err
    assert ": error: " in lines[0] and "unexpected" not in lines[0], lines[0]
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
