"""The scene walker reads a scene as Mitsuba will, or refuses it, in one line.

Each case made Mitsuba open a file the walker never checked, or cost it unbounded time:
the declared encoding (expat decoded it, pugixml reads UTF-8), a DOCTYPE's attribute
declarations (expat folds an NMTOKENS value's spaces, pugixml skips the DTD), ``L/..``
through a link (normalised by the walker, resolved by the OS for Mitsuba), objects nested
40 or 20,000 deep, and 4,000 includes of one 1 MB file parsed 4,000 times.
"""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from renderer.scenes import scenefiles
from renderer.scenes.scenefiles import MAX_NESTING, MAX_XML_BYTES, check_scene_files

SENSOR = ('<sensor type="perspective"><film type="hdrfilm"><integer name="width" value="8"/>'
          '<integer name="height" value="8"/></film></sensor>')


def mesh(name: str) -> str:
    return f'<shape type="ply"><string name="filename" value="{name}"/></shape>'


def write(path: Path, body: str, head: bytes = b"") -> Path:
    path.write_bytes(head + f'<scene version="3.0.0">{body}{SENSOR}</scene>'.encode())
    return path


def test_names_are_read_in_the_encoding_mitsuba_reads(tmp_path: Path) -> None:
    """windows-1252 declared over UTF-8 bytes: Mitsuba opens mé.ply (a FIFO), not mÃ©.ply."""
    (tmp_path / "mÃ©.ply").write_bytes(b"ply\n")
    os.mkfifo(tmp_path / "mé.ply")
    xml = write(tmp_path / "s.xml", mesh("mé.ply"), b'<?xml version="1.0" encoding="windows-1252"?>')
    with pytest.raises(ValueError, match='declares encoding="windows-1252", but Mitsuba reads it as UTF-8') as info:
        check_scene_files(xml)
    assert "\n" not in str(info.value)
    # the same bytes declared UTF-8 (or not at all) name the FIFO, and it is refused as one
    for head in (b'<?xml version="1.0" encoding="UTF-8"?>', b""):
        write(xml, mesh("mé.ply"), head)
        with pytest.raises(ValueError, match="mé.ply: mesh is a FIFO"):
            check_scene_files(xml)
    # latin1, which pugixml honours: the byte \xe9 is é for both
    xml.write_bytes(b'<?xml version="1.0" encoding="latin1"?><scene version="3.0.0">'
                    + mesh("m\xe9.ply").encode("latin-1") + b"</scene>")
    with pytest.raises(ValueError, match="mé.ply: mesh is a FIFO"):
        check_scene_files(xml)
    xml.write_bytes('<scene version="3.0.0"/>'.encode("utf-16"))
    with pytest.raises(ValueError, match="UTF-16 or UTF-32"):
        check_scene_files(xml)


def test_any_doctype_is_refused(tmp_path: Path) -> None:
    """An ATTLIST made expat read "a b.ply" where Mitsuba opens "a  b.ply" (a FIFO)."""
    (tmp_path / "a b.ply").write_bytes(b"ply\n")
    os.mkfifo(tmp_path / "a  b.ply")
    xml = write(tmp_path / "s.xml", mesh("a  b.ply"),
                b'<!DOCTYPE scene [<!ATTLIST string value NMTOKENS #IMPLIED>]>')
    with pytest.raises(ValueError, match=r"s.xml, line 1: has a DOCTYPE .*; refused$"):
        check_scene_files(xml)
    write(xml, mesh("a  b.ply"), b"<!DOCTYPE scene>")                 # no internal subset: refused too
    with pytest.raises(ValueError, match="has a DOCTYPE"):
        check_scene_files(xml)


def test_an_include_through_a_link_and_dotdot_resolves_as_the_os_does(tmp_path: Path) -> None:
    """scene/L -> other/sub: "L/../inc.xml" is other/inc.xml, whose "evil.xml" is other/evil.xml."""
    scene_dir, other = tmp_path / "scene", tmp_path / "other"
    (other / "sub").mkdir(parents=True)
    scene_dir.mkdir()
    (scene_dir / "L").symlink_to(other / "sub")
    write(other / "inc.xml", '<include filename="evil.xml"/>')
    os.mkfifo(other / "evil.xml")
    write(scene_dir / "inc.xml", "")                  # what a lexical ".." would find instead
    write(scene_dir / "evil.xml", "")
    xml = write(scene_dir / "s.xml", '<include filename="L/../inc.xml"/>')
    with pytest.raises(ValueError, match=f"{scene_dir}/L/../evil.xml: included scene is a FIFO"):
        check_scene_files(xml)


def nested(n: int) -> str:
    bsdf = '<bsdf type="diffuse"/>'
    for _ in range(n):
        bsdf = f'<bsdf type="twosided">{bsdf}</bsdf>'
    return f'<shape type="sphere">{bsdf}</shape>'


@pytest.mark.parametrize("n", [40, 20_000])
def test_deep_nesting_is_refused(tmp_path: Path, n: int) -> None:
    xml = write(tmp_path / "s.xml", nested(n))
    with pytest.raises(ValueError, match=f"objects nest deeper than {MAX_NESTING} levels") as info:
        check_scene_files(xml)
    assert "\n" not in str(info.value)
    write(xml, nested(MAX_NESTING - 3))     # scene, shape, the BSDFs: at the limit, passes
    check_scene_files(xml)


def test_nesting_counts_across_includes(tmp_path: Path) -> None:
    """An included object (not a <scene>) nests under the element including it."""
    write(tmp_path / "deep.xml", "")
    (tmp_path / "deep.xml").write_text(nested(MAX_NESTING - 3).replace('<shape type="sphere">', "", 1)
                                       .rsplit("</shape>", 1)[0])
    xml = write(tmp_path / "s.xml", '<shape type="sphere"><include filename="deep.xml"/></shape>')
    check_scene_files(xml)                  # scene 1, shape 2, BSDFs 3..16
    write(xml, '<shape type="sphere"><bsdf type="twosided"><include filename="deep.xml"/></bsdf></shape>')
    with pytest.raises(ValueError, match="deep.xml, line 1: objects nest deeper"):
        check_scene_files(xml)


def test_an_include_seen_again_is_parsed_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """50 includes of one file read it once (they were read 50 times); the bytes Mitsuba
    will parse still count each time, and past `MAX_XML_BYTES` the scene is refused."""
    write(tmp_path / "big.xml", "<!--" + "x" * 1000 + "-->")
    xml = write(tmp_path / "s.xml", '<include filename="big.xml"/>' * 50)
    reads: list[str] = []
    real_read = scenefiles.read_input
    monkeypatch.setattr(scenefiles, "read_input", lambda p, k: reads.append(os.path.basename(p)) or real_read(p, k))
    check_scene_files(xml)
    assert reads == ["s.xml", "big.xml"]
    monkeypatch.setattr(scenefiles, "MAX_XML_BYTES", 30 * 1100)
    with pytest.raises(ValueError, match="over 33000 bytes; refused"):
        check_scene_files(xml)
    assert MAX_XML_BYTES >= 1 << 30


def test_a_plugin_type_that_is_no_plain_name_is_refused(tmp_path: Path) -> None:
    """A dot would make Mitsuba load plugins/diffuse.so for "diffuse.x"; a slash, any file."""
    for bad in ("diffuse.x", "../../evil"):
        xml = write(tmp_path / "s.xml", f'<shape type="sphere"><bsdf type="{bad}"/></shape>')
        with pytest.raises(ValueError, match=f'plugin type "{bad}" is not a plain name'):
            check_scene_files(xml)


def test_loading_leaves_mitsubas_search_folders_as_they_were(tmp_path: Path) -> None:
    """A <path> in a scene resized on load was added to Mitsuba's global search folders for
    good (the field-of-view reparse ran without load_file's own resolver): every later load
    in the process, plugin libraries included, looked there first."""
    mi = pytest.importorskip("mitsuba")
    from renderer.scenes.catalog import load_scene

    (tmp_path / "sub").mkdir()
    xml = write(tmp_path / "s.xml", '<path value="sub"/><shape type="sphere"/>')
    load_scene("cornell", 8)
    before = [str(p) for p in mi.file_resolver()]
    load_scene(str(xml), (16, 8))         # resized: the sensor's fov is reparsed
    assert [str(p) for p in mi.file_resolver()] == before
