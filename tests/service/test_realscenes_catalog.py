"""The real-scene suite of `bench realscenes` (benchmarks/realscenes): each catalogued scene's
folder holds a Mitsuba 3 scene.xml whose every named file exists inside that folder (relative
names only, no <path> or <include>), rendered at 256x256 by `path` with an `independent`
sampler; the suite covers the kinds the benchmark needs and stays under 8 MB. Slow: each scene
loads through the project's own door (`load_scene`, its files checked first) and renders."""
from __future__ import annotations

import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from benchmarks.realscenes import KINDS, ROOT, SCENES, scene_path
from renderer.scenes.scenefiles import check_scene_files
from tests.support import ROOT as CHECKOUT

#: the most the suite's folder may hold, in bytes
MAX_BYTES = 8 * 1024 * 1024
#: the most bounces a scene may ask for (-1 in a source scene is capped here)
MAX_DEPTH = 12


def _named_files(xml: Path) -> list[str]:
    """Every `filename` a scene names (plugins' files, spectra, includes)."""
    root = ET.parse(xml).getroot()
    names = [e.get("value", "") for e in root.iter("string") if e.get("name") == "filename"]
    names += [e.get("filename", "") for e in root.iter() if e.tag in ("spectrum", "include") and e.get("filename")]
    return names


def _suite_files() -> list[Path]:
    return [p for p in ROOT.rglob("*") if p.is_file() and "__pycache__" not in p.parts]


def test_the_catalogue_covers_the_kinds_the_benchmark_needs() -> None:
    assert len(SCENES) >= 8
    for name, info in SCENES.items():
        assert info.name == name and info.description and set(info.kinds) <= KINDS, name
    count = {k: sum(k in s.kinds for s in SCENES.values()) for k in KINDS}
    assert count["nothing-converges"] >= 1 and count["converges"] >= 2
    for kind in ("dark", "textured", "glossy", "envmap", "small-emitters"):
        assert count[kind] >= 1, kind
    assert not any("nothing-converges" in s.kinds and "converges" in s.kinds for s in SCENES.values())


@pytest.mark.parametrize("name", sorted(SCENES))
def test_each_scene_names_only_files_inside_its_folder(name: str) -> None:
    xml = scene_path(name)
    folder = xml.parent
    assert xml.is_file() and folder.parent == ROOT
    root = ET.parse(xml).getroot()
    assert root.tag == "scene" and root.get("version") == "3.0.0"
    assert not list(root.iter("path")) and not list(root.iter("include"))
    names = _named_files(xml)
    assert names, "a real scene names its meshes"
    for n in names:
        assert not Path(n).is_absolute() and "$" not in n, n
        target = (folder / n).resolve()
        assert target.is_relative_to(folder.resolve()), f"{n} lies outside {folder.name}/"
        assert target.is_file(), f"{name}: {n} is missing"
    check_scene_files(xml, search=[str(folder)])      # the project's own walk agrees


@pytest.mark.parametrize("name", sorted(SCENES))
def test_each_scene_renders_256_square_with_path_and_independent(name: str) -> None:
    root = ET.parse(scene_path(name)).getroot()
    (integrator,) = root.findall("integrator")
    assert integrator.get("type") == "path"
    depth = {e.get("name"): int(e.get("value")) for e in integrator.findall("integer")}.get("max_depth")
    assert depth is not None and 1 <= depth <= MAX_DEPTH
    (sensor,) = root.findall("sensor")
    assert sensor.find("sampler").get("type") == "independent"
    film = sensor.find("film")
    assert film.get("type") == "hdrfilm"
    size = {e.get("name"): int(e.get("value")) for e in film.findall("integer")}
    assert (size.get("width"), size.get("height")) == (256, 256)
    assert film.find("rfilter").get("type") in ("box", "gaussian")


def test_the_suite_fits_the_repository() -> None:
    files = _suite_files()
    assert sum(p.stat().st_size for p in files) < MAX_BYTES
    assert not [p for p in ROOT.rglob("*") if p.is_dir() and p.name == "plugins"]
    assert (ROOT / "SOURCES.md").is_file()
    sources = (ROOT / "SOURCES.md").read_text()
    assert all(f"`{name}`" in sources for name in SCENES)
    # every file in a scene's folder is one its scene names (nothing stray is carried)
    for name in SCENES:
        folder = scene_path(name).parent
        named = {(folder / n).resolve() for n in _named_files(scene_path(name))} | {scene_path(name).resolve()}
        assert {p.resolve() for p in folder.rglob("*") if p.is_file()} == named, name


def test_the_catalogue_imports_no_mitsuba() -> None:
    code = "import sys, benchmarks.realscenes as r; r.scene_path('cbox'); print('mitsuba' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], cwd=CHECKOUT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_an_unknown_scene_is_named_in_the_error() -> None:
    with pytest.raises(KeyError, match="cbox"):
        scene_path("no-such-scene")


@pytest.mark.slow
def test_each_scene_loads_through_the_door_and_renders() -> None:
    """Each scene through `load_scene` (its files checked first), 16x16 at 4 spp: finite,
    and, but for the dark ones (lit through glass: 4 spp may find no light), not all black."""
    import numpy as np

    from renderer.scenes.catalog import load_scene

    mi = pytest.importorskip("mitsuba")
    for name in SCENES:
        scene = load_scene(scene_path(name), resolution=16)
        assert tuple(scene.sensors()[0].film().size()) == (16, 16), name
        img = np.asarray(mi.render(scene, spp=4, seed=0))
        assert np.isfinite(img).all(), name
        assert "dark" in SCENES[name].kinds or img.max() > 0, name
