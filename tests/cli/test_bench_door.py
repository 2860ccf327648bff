"""`noisestop bench` is a door: it runs the benchmarks of the source checkout the packages
live in, from any working directory, and without a checkout it is one line (exit 2).
The plain install itself (an unpacked wheel) is tests/project/test_wheel.py's."""
from __future__ import annotations

import json
import os
import subprocess
import sys

from service import cli
from service.commands import bench as door
from tests.support import ROOT
from tests.support.errors import assert_one_line_error


def test_the_door_finds_this_checkout() -> None:
    assert door.checkout_root() == ROOT
    module = door.load_benchmarks()
    assert module.__name__ == "benchmarks.bench" and module.__file__ == str(ROOT / "benchmarks" / "bench.py")


def test_bench_runs_a_section_from_another_directory(tmp_path) -> None:
    """`noisestop bench stability --json` in a folder outside the checkout, with no
    PYTHONPATH: the door finds the benchmarks beside the installed packages."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "NOISESTOP_DEBUG")}
    out = subprocess.run([sys.executable, "-c", "import sys; from service.cli import main; sys.exit(main())",
                          "bench", "stability", "--json"], cwd=tmp_path, env=env, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    results = json.loads(out.stdout)
    assert results["failed"] == {} and "stability" in json.dumps(results)


def test_without_a_checkout_bench_is_one_line(monkeypatch, capsys) -> None:
    monkeypatch.setattr(door, "checkout_root", lambda: None)
    rc = cli.main(["bench", "stability"])
    err = capsys.readouterr().err
    assert_one_line_error(rc, err, "source checkout")
    assert err.startswith("noisestop bench: error: the benchmarks run from a source checkout")
