"""Every file a scene XML names is checked before Mitsuba opens it.

Each kind of named file (a ply mesh, an <include>, a bitmap texture, an environment map) as
/dev/zero, a FIFO, a 3 GB sparse file and a missing file: refused in one line naming the file
and the element, within seconds (unchecked, a ply of /dev/zero grew to 7.6 GB and an
include of a FIFO hung). The walk resolves names as Mitsuba does and follows -D and <default>.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from renderer.scenes.catalog import load_scene
from renderer.scenes.scenefiles import MAX_DEPTH, check_scene_files
from tests.support.bad_files import bad_file as make_bad_file
from tests.support.errors import assert_one_line_error, run

SENSOR = ('<sensor type="perspective"><film type="hdrfilm"><integer name="width" value="8"/>'
          '<integer name="height" value="8"/></film></sensor>')
#: an element naming NAME, by the kind of file it names
NAMING = {
    "mesh": '<shape type="ply"><string name="filename" value="{name}"/></shape>',
    "include": '<include filename="{name}"/>',
    "bitmap": ('<shape type="sphere"><bsdf type="diffuse"><texture type="bitmap" name="reflectance">'
               '<string name="filename" value="{name}"/></texture></bsdf></shape>'),
    "envmap": '<emitter type="envmap"><string name="filename" value="{name}"/></emitter>',
}
ELEMENT = {"mesh": '<shape type="ply">', "include": "<include>", "bitmap": '<texture type="bitmap">',
           "envmap": '<emitter type="envmap">'}
BAD = ("/dev/zero", "FIFO", "3 GB sparse", "missing")


def scene(tmp: Path, body: str, name: str = "scene.xml") -> Path:
    path = tmp / name
    path.write_text(f'<scene version="3.0.0">{body}{SENSOR}</scene>')
    return path


def bad_file(tmp: Path, kind: str) -> Path:
    return make_bad_file(tmp / "bad.dat", kind)


@pytest.mark.parametrize("bad", BAD)
@pytest.mark.parametrize("element", list(NAMING))
def test_a_named_file_that_is_no_regular_file_is_refused(tmp_path, element, bad):
    target = bad_file(tmp_path, bad)
    xml = scene(tmp_path, NAMING[element].format(name=target.name))     # relative: the XML's folder
    t0 = time.perf_counter()
    with pytest.raises((ValueError, FileNotFoundError)) as info:
        load_scene(str(xml), 16)
    assert time.perf_counter() - t0 < 60        # a refusal, not a hang (its speed: bench hardening)
    msg = str(info.value)
    shown = f"not found in {tmp_path}," if bad == "missing" else f"{tmp_path}/bad.dat: "   # missing: where
    assert "\n" not in msg and shown in msg and ELEMENT[element] in msg, msg
    assert f"{xml}, line 1" in msg
    assert {"/dev/zero": "a device", "FIFO": "a FIFO", "3 GB sparse": "over the limit",
            "missing": "bad.dat: "}[bad] in msg


def test_the_command_line_refuses_it_in_one_line(tmp_path, capsys):
    os.mkfifo(tmp_path / "mesh.ply")
    xml = scene(tmp_path, NAMING["mesh"].format(name="mesh.ply"))
    rc, err = run(capsys, "render", "--scene", str(xml), "--resolution", "16", "--out", str(tmp_path / "o"))
    assert_one_line_error(rc, err, str(tmp_path / "mesh.ply"), "is a FIFO", '<shape type="ply">')


def test_defines_and_defaults_name_the_file_as_mitsuba_reads_it(tmp_path):
    os.mkfifo(tmp_path / "fifo.ply")
    xml = scene(tmp_path, '<default name="mesh" value="fine"/>'
                + NAMING["mesh"].format(name="$mesh.ply"))
    with pytest.raises(ValueError, match="fifo.ply: mesh is a FIFO"):
        check_scene_files(xml, {"mesh": "fifo"})
    with pytest.raises(FileNotFoundError, match="fine.ply: mesh not found in"):
        check_scene_files(xml)               # the <default>, resolved against the current folder last


def test_a_plugin_file_in_an_include_resolves_against_the_top_file(tmp_path):
    """Mitsuba loads plugins with the top file's resolver: an include's folder is not searched."""
    (tmp_path / "sub").mkdir()
    os.mkfifo(tmp_path / "m.ply")
    (tmp_path / "sub" / "m.ply").write_bytes(b"ply\n")
    (tmp_path / "sub" / "inc.xml").write_text(f'<scene version="3.0.0">{NAMING["mesh"].format(name="m.ply")}</scene>')
    xml = scene(tmp_path, '<include filename="sub/inc.xml"/>')
    with pytest.raises(ValueError, match=f"{tmp_path / 'm.ply'}: mesh is a FIFO.*sub/inc.xml, line 1"):
        check_scene_files(xml)


def test_include_loops_and_depth_are_refused(tmp_path):
    loop = scene(tmp_path, '<include filename="b.xml"/>', "a.xml")
    scene(tmp_path, '<include filename="a.xml"/>', "b.xml")
    with pytest.raises(ValueError, match="include loop"):
        check_scene_files(loop)
    for i in range(MAX_DEPTH + 1):
        scene(tmp_path, f'<include filename="d{i + 1}.xml"/>', f"d{i}.xml")
    with pytest.raises(ValueError, match="nest deeper"):
        check_scene_files(tmp_path / "d0.xml")


def test_entity_declarations_are_refused(tmp_path):
    xml = tmp_path / "lol.xml"
    xml.write_text('<!DOCTYPE s [<!ENTITY a "aaaaaaaaaa"><!ENTITY b "&a;&a;&a;&a;">]>'
                   f'<scene version="3.0.0">{SENSOR}</scene>')
    with pytest.raises(ValueError, match="entity"):
        load_scene(str(xml))


def test_a_scene_with_a_real_mesh_still_loads(tmp_path):
    """Control: a ply beside the XML and one found through <path> load as before."""
    mi = pytest.importorskip("mitsuba")
    import numpy as np

    load_scene("cornell", 16)         # a variant
    mesh = mi.Mesh("m", 3, 1)
    params = mi.traverse(mesh)
    params["vertex_positions"] = np.array([0, 0, 0, 1, 0, 0, 0, 1, 0], np.float32)
    params["faces"] = np.array([0, 1, 2], np.uint32)
    params.update()
    (tmp_path / "meshes").mkdir()
    mesh.write_ply(str(tmp_path / "meshes" / "m.ply"))
    xml = scene(tmp_path, '<path value="meshes"/>' + NAMING["mesh"].format(name="m.ply"))
    assert len(load_scene(str(xml), 16).shapes()) == 1
