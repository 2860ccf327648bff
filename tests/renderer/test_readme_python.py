"""README "Python": the example is at most ten lines and runs as written.

It renders Mitsuba's Cornell box (256x256); the test shrinks that scene's film to 64x64
before the example runs (a prelude replaces `mi.cornell_box`), the example's own text
unchanged, so it takes seconds.
"""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import pytest

from tests.support import ROOT

PRELUDE = """
import mitsuba as mi
_cornell_box = mi.cornell_box
def _small_cornell_box():
    d = _cornell_box()
    d["sensor"]["film"].update(width=64, height=64)
    return d
mi.cornell_box = _small_cornell_box
"""


def readme_example() -> str:
    text = (ROOT / "README.md").read_text()
    section = text[text.index("\n## Python\n"):]
    section = section[:section.index("\n## ", 1)]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_the_example_is_at_most_ten_lines():
    code = readme_example()
    assert len(code.strip().splitlines()) <= 10
    assert "renderer.render(" in code and ".save(" in code and ".spp" in code and "mi.load_" in code
    compile(code, "README.md", "exec")


@pytest.mark.slow
def test_the_example_runs(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-c", PRELUDE + readme_example()], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert re.fullmatch(r"mean spp \d+ of 1024, \d+% of the samples saved\n", out.stdout), out.stdout
    assert {p.name for p in (tmp_path / "out").iterdir()} == {"final.exr", "final.png", "spp_map.png",
                                                              "report.json"}
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["resolution"] == [64, 64] and report["criterion"]["name"] == "flip"
