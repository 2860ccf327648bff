"""No code is loaded from a scene's folders or the current one.

Mitsuba looks a plugin's library up as ``plugins/<type>.so`` through its file resolver,
which holds the scene's folder (and the current folder) before Mitsuba's own: a
``plugins/diffuse.so`` beside a scene ran its code when the scene was rendered. Here a real
library, built with gcc, whose constructor writes a marker file, sits where Mitsuba would
find it; each door runs in a fresh process (Mitsuba caches libraries per process), and the
marker must not appear. The scene is refused in one line where it names such a library;
a built-in scene in a folder holding one renders with Mitsuba's own.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support import ROOT
from tests.support.errors import assert_one_line_error

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(shutil.which("gcc") is None, reason="gcc builds the planted library")]

SCENE = """<scene version="3.0.0">
  <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="8"/>
    <integer name="height" value="8"/></film></sensor>
  <shape type="sphere"><bsdf type="{bsdf}"/></shape>
</scene>
"""


def plant(folder: Path, name: str, marker: Path) -> None:
    """`folder`/plugins/`name`.so, whose constructor writes `marker`."""
    (folder / "plugins").mkdir(parents=True, exist_ok=True)
    source = folder / f"{name}.c"
    source.write_text('#include <stdio.h>\n__attribute__((constructor)) static void ran(void) {\n'
                      f'  FILE *f = fopen("{marker}", "w"); if (f) {{ fputs("ran", f); fclose(f); }}\n}}\n')
    subprocess.run(["gcc", "-shared", "-fPIC", "-o", str(folder / "plugins" / f"{name}.so"), str(source)],
                   check=True, capture_output=True, timeout=120)


def noisestop(cwd: Path, *argv: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-m", "service.cli", "-q", *argv], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("bsdf", ["diffuse", "evil"])
def test_a_library_beside_the_scene_is_never_loaded(tmp_path: Path, bsdf: str) -> None:
    """A built-in name (diffuse) and one that is not (evil): refused, the code never ran."""
    folder, marker = tmp_path / "scene", tmp_path / "marker"
    plant(folder, bsdf, marker)
    (folder / "scene.xml").write_text(SCENE.format(bsdf=bsdf))
    proc = noisestop(tmp_path, "render", "--scene", str(folder / "scene.xml"), "--out", str(tmp_path / "out"),
                     "--criterion", "uniform", "--max-spp", "4")
    assert not marker.exists(), "the planted library's code ran"
    assert_one_line_error(proc.returncode, proc.stderr, f"{folder}/plugins/{bsdf}.so: a plugin library",
                          f'<bsdf type="{bsdf}">')


def test_a_library_in_the_current_folder_is_never_loaded(tmp_path: Path) -> None:
    """A built-in scene (Mitsuba names diffuse itself) run from a folder holding
    plugins/diffuse.so renders with Mitsuba's own library."""
    marker = tmp_path / "marker"
    plant(tmp_path, "diffuse", marker)
    proc = noisestop(tmp_path, "render", "--scene", "cornell", "--resolution", "16", "--out", str(tmp_path / "out"),
                     "--criterion", "uniform", "--max-spp", "4", "--min-spp", "4", "--step", "4")
    assert not marker.exists(), "the planted library's code ran"
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "out" / "report.json").is_file()
