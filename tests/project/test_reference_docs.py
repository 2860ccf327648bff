"""The reference pages (docs/reference/settings.md, docs/reference/cli.md) are what
docs/gen_reference.py writes from the code: a render spec row or a command-line option
changed without regenerating them fails here.

The check runs the generator in a fresh process: a criterion a test declares on import
(tests/support/plugin_criterion.py) would otherwise show in the rows' help text."""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from dataclasses import replace

from tests.support import ROOT

GENERATOR = ROOT / "docs" / "gen_reference.py"


def _generator():
    spec = importlib.util.spec_from_file_location("gen_reference", GENERATOR)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_committed_reference_pages_are_current() -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, str(GENERATOR), "--check"], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-3000:]


def test_the_pages_cover_every_row_and_every_command() -> None:
    from renderer.settings import ROWS
    from service.cli import build_parser

    gen = _generator()
    settings = (ROOT / gen.SETTINGS).read_text()
    cli = (ROOT / gen.CLI).read_text()
    assert all(f"| `{row.name}` |" in settings for row in ROWS)
    commands = [name for name, _, _ in gen._subparsers(build_parser())]
    assert len(commands) >= 9 and all(f"## `noisestop {name}`" in cli for name in commands)
    assert "`--decide-growth`" in cli and "### `noisestop dataset build`" in cli


def test_a_changed_row_or_option_is_found(tmp_path) -> None:
    """Control: the committed pages, then a row with another default and a parser with one
    more option: each makes its page stale, and nothing else."""
    from renderer.settings import ROWS
    from service.cli import build_parser

    gen = _generator()
    for rel in (gen.SETTINGS, gen.CLI):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text((ROOT / rel).read_text())
    tau = next(i for i, row in enumerate(ROWS) if row.name == "tau")
    rows = list(ROWS)
    rows[tau] = replace(rows[tau], default=0.03)
    assert gen.stale(tmp_path, {gen.SETTINGS: gen.settings_page(rows)}) == [gen.SETTINGS]

    parser = build_parser()
    render = next(sub for name, _, sub in gen._subparsers(parser) if name == "render")
    render.add_argument("--new-knob", type=int, default=3, help="a knob the page does not list")
    assert gen.stale(tmp_path, {gen.CLI: gen.cli_page(parser)}) == [gen.CLI]
