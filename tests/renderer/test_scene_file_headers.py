"""Decompression bombs under the size caps: the images and meshes a scene
names are bounded by what their headers state, before Mitsuba decodes them.

A 1.2 MB PNG of 20000 x 20000 grew a render past 2.5 GB, as did a sparse obj just under
the 2 GiB mesh cap: only sizes were checked. For each format Mitsuba reads, a small real
file passes (Mitsuba's own reading of it agrees with the header's size) and a forged header
stating 20000 x 20000 pixels, a billion elements, or a line as long as the file is refused
in one line naming the file and the element naming it.
"""
from __future__ import annotations

import struct
import zlib
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from noisefeat import safeio
from renderer.scenes.scenefiles import check_scene_files

SENSOR = ('<sensor type="perspective"><film type="hdrfilm"><integer name="width" value="8"/>'
          '<integer name="height" value="8"/></film></sensor>')
BIG = 20000


def scene(tmp: Path, element: str, name: str) -> Path:
    body = {"bitmap": ('<shape type="sphere"><bsdf type="diffuse"><texture type="bitmap" name="reflectance">'
                       f'<string name="filename" value="{name}"/></texture></bsdf></shape>'),
            "envmap": f'<emitter type="envmap"><string name="filename" value="{name}"/></emitter>',
            "volume": ('<medium type="heterogeneous"><volume type="gridvolume" name="sigma_t">'
                       f'<string name="filename" value="{name}"/></volume></medium>')}.get(
        element, f'<shape type="{element}"><string name="filename" value="{name}"/></shape>')
    path = tmp / "scene.xml"
    path.write_text(f'<scene version="3.0.0">{body}{SENSOR}</scene>')
    return path


def mitsuba() -> object:
    """Mitsuba with the variant the renderer chooses (tests after these expect it)."""
    mi = pytest.importorskip("mitsuba")
    from learning.data.variant import select_variant

    select_variant()
    return mi


def mitsuba_size(path: Path) -> tuple[int, int]:
    mi = mitsuba()
    return tuple(int(v) for v in mi.Bitmap(str(path)).size())


def written(ext: str) -> Callable[[Path, int, int], bytes]:
    """An image of `ext` as Mitsuba's Bitmap writes it."""
    def make(path: Path, w: int, h: int) -> bytes:
        mi = mitsuba()
        bitmap = mi.Bitmap(np.full((h, w, 3), 0.5, np.float32))
        if ext in ("png", "jpg", "ppm"):
            bitmap = bitmap.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, True)
        bitmap.write(str(path))
        return path.read_bytes()
    return make


def tga(path: Path, w: int, h: int) -> bytes:
    data = struct.pack("<BBB5sHHHHBB", 0, 0, 2, b"", 0, 0, w, h, 24, 0) + bytes(3 * w * h)
    return data + bytes(8) + b"TRUEVISION-XFILE.\0"


def bmp(path: Path, w: int, h: int) -> bytes:
    row = (3 * w + 3) & ~3
    return (b"BM" + struct.pack("<IHHI", 54 + row * h, 0, 0, 54) + struct.pack("<IiiHHI", 40, w, h, 1, 24, 0)
            + bytes(20) + bytes(row * h))


#: format: (a real file of w x h, a forged header of BIG x BIG)
IMAGES: dict[str, tuple[Callable[[Path, int, int], bytes], bytes]] = {
    "png": (written("png"), b"\x89PNG\r\n\x1a\n" + struct.pack(">I4sIIBBBBB", 13, b"IHDR", BIG, BIG, 8, 2, 0, 0, 0)),
    "jpg": (written("jpg"), b"\xff\xd8\xff\xe0\x00\x10JFIF\x00\x01\x01\x00\x00\x01\x00\x01\x00\x00"
                            + b"\xff\xc0" + struct.pack(">HBHHB", 17, 8, BIG, BIG, 3) + bytes(9)),
    "exr": (written("exr"), b"\x76\x2f\x31\x01" + struct.pack("<I", 2) + b"dataWindow\0box2i\0"
                            + struct.pack("<i4i", 16, 0, 0, BIG - 1, BIG - 1) + b"\0" + bytes(64)),
    "hdr": (written("hdr"), f"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y {BIG} +X {BIG}\n".encode() + bytes(64)),
    "pfm": (written("pfm"), f"PF\n{BIG} {BIG}\n-1\n".encode() + bytes(64)),
    "ppm": (written("ppm"), f"P6\n{BIG} {BIG}\n255\n".encode() + bytes(64)),
    "tga": (tga, tga(Path(), 1, 1)[:12] + struct.pack("<hh", BIG, BIG) + tga(Path(), 1, 1)[16:]),
    "bmp": (bmp, bmp(Path(), 1, 1)[:18] + struct.pack("<ii", BIG, BIG) + bmp(Path(), 1, 1)[26:]),
}


@pytest.mark.parametrize("element", ["bitmap", "envmap"])
@pytest.mark.parametrize("fmt", list(IMAGES))
def test_an_image_stating_too_many_pixels_is_refused(tmp_path: Path, fmt: str, element: str) -> None:
    real, forged = IMAGES[fmt]
    good = tmp_path / f"good.{fmt}"
    good.write_bytes(real(good, 5, 3))
    assert mitsuba_size(good) == (5, 3)              # a file Mitsuba reads, as it reads it
    check_scene_files(scene(tmp_path, element, good.name))
    bad = tmp_path / f"bomb.{fmt}"
    bad.write_bytes(forged)
    with pytest.raises(ValueError) as info:
        check_scene_files(scene(tmp_path, element, bad.name))
    msg = str(info.value)
    assert "\n" not in msg and f"{bad}: " in msg and f"of {BIG} x {BIG} pixels, over the limit" in msg, msg
    assert ('<texture type="bitmap">' if element == "bitmap" else '<emitter type="envmap">') in msg


def test_an_image_whose_header_cannot_be_read_is_refused(tmp_path: Path) -> None:
    (tmp_path / "x.png").write_bytes(b"#?RADIANCE\n" + b"A" * (100 << 10))     # no resolution line
    with pytest.raises(ValueError, match="x.png: texture has no header Mitsuba could read"):
        check_scene_files(scene(tmp_path, "bitmap", "x.png"))
    (tmp_path / "x.png").write_bytes(b"GIF89a" + bytes(64))
    with pytest.raises(ValueError, match="not a PNG, JPEG, OpenEXR"):
        check_scene_files(scene(tmp_path, "bitmap", "x.png"))


def ply(vertices: int, faces: int, data: bytes) -> bytes:
    return (f"ply\nformat binary_little_endian 1.0\ncomment end_header\nelement vertex {vertices}\n"
            "property float x\nproperty float y\nproperty float z\n"
            f"element face {faces}\nproperty list uchar int vertex_indices\nend_header\n").encode() + data


def serialized(vertices: int, faces: int, body: bytes = b"") -> bytes:
    return struct.pack("<hh", 0x041C, 4) + zlib.compress(struct.pack("<I", 0) + b"m\0"
                                                         + struct.pack("<QQ", vertices, faces) + body)


def vol(x: int, y: int, z: int, data: bytes) -> bytes:
    return b"VOL\x03" + struct.pack("<5i6f", 1, x, y, z, 1, 0, 0, 0, 1, 1, 1) + data


TRIANGLE = struct.pack("<9f", 0, 0, 0, 1, 0, 0, 0, 1, 0)
#: element: (a real file, a forged one, what the refusal says)
MESHES = {
    "ply": (ply(3, 1, TRIANGLE + struct.pack("<B3i", 3, 0, 1, 2)), ply(10 ** 9, 1, TRIANGLE), "states 1000000001 elements"),
    "obj": (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", None, "has a line of 1024 bytes or more"),
    "serialized": (serialized(3, 1, TRIANGLE + struct.pack("<3I", 0, 1, 2)), serialized(10 ** 9, 10 ** 9),
                   "states 2000000000 vertices and faces"),
    "volume": (vol(2, 2, 2, bytes(32)), vol(1000, 1000, 1000, bytes(64)), "states a 1000 x 1000 x 1000 grid"),
    "sdfgrid": (vol(2, 2, 2, bytes(32)), vol(1000, 1000, 1000, bytes(64)), "states a 1000 x 1000 x 1000 grid"),
}


@pytest.mark.parametrize("element", list(MESHES))
def test_a_mesh_stating_too_many_elements_is_refused(tmp_path: Path, element: str) -> None:
    real, forged, why = MESHES[element]
    (tmp_path / "good.dat").write_bytes(real)
    check_scene_files(scene(tmp_path, element, "good.dat"))
    bad = tmp_path / "bomb.dat"
    if forged is None:                     # a sparse obj just under the mesh cap: one hole of a line
        with open(bad, "wb") as f:
            f.write(real)
            f.truncate(safeio.CAPS["mesh"] - 1)
    else:
        bad.write_bytes(forged)
    with pytest.raises(ValueError) as info:
        check_scene_files(scene(tmp_path, element, "bomb.dat"))
    msg = str(info.value)
    assert "\n" not in msg and f"{bad}: " in msg and why in msg and "refused" in msg, msg


def test_a_ply_cut_short_and_an_obj_of_too_many_words_are_refused(tmp_path: Path, monkeypatch) -> None:
    (tmp_path / "m.ply").write_bytes(ply(1000, 0, TRIANGLE))
    with pytest.raises(ValueError, match="states elements of 12000 bytes at least, but holds 36"):
        check_scene_files(scene(tmp_path, "ply", "m.ply"))
    monkeypatch.setitem(safeio.CAPS, "mesh elements", 1000)
    (tmp_path / "m.obj").write_bytes(b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + (b"f" + b" 1" * 400 + b"\n") * 3)
    with pytest.raises(ValueError, match=r"m.obj: mesh states 1215 elements at most \(its words\), over the limit of 1000"):
        check_scene_files(scene(tmp_path, "obj", "m.obj"))


def test_a_serialized_shape_is_read_where_its_shape_index_points(tmp_path: Path) -> None:
    """A two-shape file (the table of offsets at its end, as Mitsuba writes it): shape 0 is
    a triangle, shape 1 states two billion elements; only shape_index 1 is refused."""
    first = serialized(3, 1, TRIANGLE + struct.pack("<3I", 0, 1, 2))
    second = serialized(10 ** 9, 10 ** 9)
    (tmp_path / "two.serialized").write_bytes(first + second + struct.pack("<QQI", 0, len(first), 2))
    shape = ('<shape type="serialized"><string name="filename" value="two.serialized"/>'
             '<integer name="shape_index" value="{}"/></shape>')
    xml = tmp_path / "scene.xml"
    xml.write_text(f'<scene version="3.0.0">{shape.format(0)}{SENSOR}</scene>')
    check_scene_files(xml)
    mi = mitsuba()
    assert mi.load_dict({"type": "serialized", "filename": str(tmp_path / "two.serialized")}).face_count() == 1
    xml.write_text(f'<scene version="3.0.0">{shape.format(1)}{SENSOR}</scene>')
    with pytest.raises(ValueError, match="two.serialized: mesh states 2000000000 vertices and faces"):
        check_scene_files(xml)
