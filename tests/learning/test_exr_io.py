"""EXR and PNG I/O without Mitsuba (OpenEXR, Pillow): files Mitsuba wrote read back bit for
bit as mitsuba.Bitmap read them, Mitsuba reads what we write, damaged files are one
ValueError naming them, and none of it imports Mitsuba."""
from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from learning.data.exr import read_exr, read_exr_channels, read_png, write_exr, write_exr_channels, write_png
from tests.support import ROOT

FIXTURE_EXRS = sorted((ROOT / "tests" / "fixtures" / "dataset").glob("*/**/*.exr")) + sorted(
    (ROOT / "examples" / "references").glob("*.exr"))


@pytest.fixture(scope="module")
def mi():
    pytest.importorskip("mitsuba")
    from learning.data.variant import select_variant

    select_variant()
    import mitsuba

    return mitsuba


def _tricky(h=48, w=40, seed=0) -> np.ndarray:
    """Float32 RGB over 45 stops, with NaN, +-Inf, signed zeros, subnormals and values at
    the half-float overflow and rounding edges."""
    rng = np.random.default_rng(seed)
    x = (rng.standard_normal((h, w, 3)) * np.exp(rng.uniform(-30, 15, (h, w, 3)))).astype(np.float32)
    x[0, 0] = [np.nan, np.inf, -np.inf]
    x[0, 1] = [65504, 65520, 65519.99]
    x[0, 2] = [1e-8, 6e-8, 3e-8]
    x[0, 3] = [-0.0, 0.0, 2.9802322e-08]
    x[0, 4] = [1e-42, -1e-40, 3.4e38]
    return x


def _mitsuba_read(mi, path: Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """What the Mitsuba-based reader returned: RGB float32, and every channel by name."""
    bm = mi.Bitmap(str(path), mi.Bitmap.FileFormat.OpenEXR)
    names = [f.name for f in bm.struct_()]
    data = np.array(bm, copy=True).astype(np.float32).reshape(bm.height(), bm.width(), len(names))
    channels = {n: data[..., i] for i, n in enumerate(names)}
    if bm.pixel_format() == mi.Bitmap.PixelFormat.MultiChannel:
        rgb = np.stack([channels[c] for c in "RGB"], axis=-1)
    else:
        rgb = np.array(bm.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, srgb_gamma=False),
                       dtype=np.float32, copy=True)
    return rgb, channels


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def _assert_reads_as_mitsuba(mi, path: Path) -> None:
    rgb, channels = _mitsuba_read(mi, path)
    ours = read_exr_channels(path)
    assert _same_bits(read_exr(path), rgb), path
    assert list(ours) == list(channels), path
    assert all(_same_bits(ours[n], channels[n]) for n in channels), path


# ----------------------------------------------------------------------------- against Mitsuba

def test_the_fixture_files_read_bit_for_bit_as_mitsuba_read_them(mi):
    """Levels, references and quick images (float32) and the shipped half reference."""
    assert len(FIXTURE_EXRS) > 60
    kinds = set()
    for path in FIXTURE_EXRS:
        _assert_reads_as_mitsuba(mi, path)
        kinds.add(mi.Bitmap(str(path)).component_format())
    assert kinds == {mi.Struct.Type.Float32, mi.Struct.Type.Float16}


def test_files_mitsuba_writes_read_bit_for_bit(mi, tmp_path):
    """float32 and half RGB, RGBA, grey, and final.exr's multi-channel layout (R, G, B, spp,
    converged) as the Mitsuba-based writer made them."""
    x = _tricky()
    rgb = mi.Bitmap(x, pixel_format=mi.Bitmap.PixelFormat.RGB)
    rgb.write(str(tmp_path / "f32.exr"))
    rgb.convert(component_format=mi.Struct.Type.Float16).write(str(tmp_path / "f16.exr"))
    rgba = np.concatenate([x, np.full(x.shape[:2] + (1,), 0.25, np.float32)], axis=2)
    mi.Bitmap(rgba, pixel_format=mi.Bitmap.PixelFormat.RGBA).write(str(tmp_path / "rgba.exr"))
    mi.Bitmap(np.ascontiguousarray(x[..., 1])).write(str(tmp_path / "grey.exr"))
    spp = np.random.default_rng(1).integers(16, 4096, x.shape[:2]).astype(np.float32)
    final = np.stack([x[..., 0], x[..., 1], x[..., 2], spp, (spp > 2000).astype(np.float32)], axis=-1)
    mi.Bitmap(np.ascontiguousarray(final), pixel_format=mi.Bitmap.PixelFormat.MultiChannel,
              channel_names=["R", "G", "B", "spp", "converged"]).write(str(tmp_path / "final.exr"))
    for name in ("f32", "f16", "rgba", "grey", "final"):
        _assert_reads_as_mitsuba(mi, tmp_path / f"{name}.exr")
    assert list(read_exr_channels(tmp_path / "final.exr")) == ["R", "G", "B", "converged", "spp"]
    np.testing.assert_array_equal(read_exr_channels(tmp_path / "final.exr")["spp"], spp)


def test_mitsuba_reads_what_we_write(mi, tmp_path):
    """float32 exactly; half with the very bits Mitsuba's own float16 conversion gives;
    named channels."""
    x = _tricky(seed=2)
    write_exr(tmp_path / "f32.exr", x)
    write_exr(tmp_path / "f16.exr", x, half=True)
    spp = np.arange(x.shape[0] * x.shape[1], dtype=np.float32).reshape(x.shape[:2])
    write_exr_channels(tmp_path / "final.exr", {"R": x[..., 0], "G": x[..., 1], "B": x[..., 2],
                                                "spp": spp, "converged": spp % 2})
    assert _same_bits(_mitsuba_read(mi, tmp_path / "f32.exr")[0], x)
    half = mi.Bitmap(x, pixel_format=mi.Bitmap.PixelFormat.RGB).convert(component_format=mi.Struct.Type.Float16)
    assert mi.Bitmap(str(tmp_path / "f16.exr")).component_format() == mi.Struct.Type.Float16
    assert _same_bits(_mitsuba_read(mi, tmp_path / "f16.exr")[0], np.array(half).astype(np.float32))
    _, channels = _mitsuba_read(mi, tmp_path / "final.exr")
    assert _same_bits(channels["spp"], spp) and _same_bits(channels["converged"], spp % 2)
    assert _same_bits(np.stack([channels[c] for c in "RGB"], -1), x)
    for name in ("f32", "f16", "final"):
        _assert_reads_as_mitsuba(mi, tmp_path / f"{name}.exr")


def test_mitsuba_reads_our_png_as_we_do(mi, tmp_path):
    u8 = np.random.default_rng(3).integers(0, 256, (9, 13, 3), dtype=np.uint8)
    write_png(tmp_path / "p.png", u8)
    bm = mi.Bitmap(str(tmp_path / "p.png"))
    assert bm.component_format() == mi.Struct.Type.UInt8
    np.testing.assert_array_equal(np.array(bm), u8)
    # Mitsuba's float conversion went through linear light and back (up to 2.4e-7 off);
    # read_png gives v / 255 exactly rounded.
    old = np.array(bm.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, srgb_gamma=True))
    np.testing.assert_allclose(read_png(tmp_path / "p.png"), old, rtol=0, atol=3e-7)


# ----------------------------------------------------------------------------- without Mitsuba

def test_float32_half_and_channels_round_trip(tmp_path):
    x = _tricky(seed=4)
    write_exr(tmp_path / "a.exr", x)
    assert _same_bits(read_exr(tmp_path / "a.exr"), x)
    write_exr(tmp_path / "h.exr", x, half=True)
    with np.errstate(over="ignore"):
        assert _same_bits(read_exr(tmp_path / "h.exr"), x.astype(np.float16).astype(np.float32))
    ch = {"R": x[..., 0], "G": x[..., 1], "B": x[..., 2], "spp": np.full(x.shape[:2], 3.0),
          "converged": np.zeros(x.shape[:2])}
    write_exr_channels(tmp_path / "c.exr", ch)
    back = read_exr_channels(tmp_path / "c.exr")
    assert list(back) == ["R", "G", "B", "converged", "spp"]
    assert all(_same_bits(back[k], np.asarray(v, np.float32)) for k, v in ch.items())
    assert _same_bits(read_exr(tmp_path / "c.exr"), x)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.exr", "c.exr", "h.exr"]   # no temp files


def test_every_truncation_is_a_value_error_naming_the_file(tmp_path):
    p = tmp_path / "cut.exr"
    write_exr_channels(p, {"R": np.ones((70, 9), np.float32), "spp": np.zeros((70, 9), np.float32)})
    data = p.read_bytes()
    for n in range(len(data)):
        p.write_bytes(data[:n])
        with pytest.raises(ValueError, match="cut.exr"):
            read_exr_channels(p)
    p.write_bytes(data)
    assert read_exr_channels(p)["R"].shape == (70, 9)


def test_bad_files_and_shapes(tmp_path):
    (tmp_path / "junk.exr").write_bytes(b"this is not an exr file at all")
    with pytest.raises(ValueError, match="junk.exr: not an EXR"):
        read_exr(tmp_path / "junk.exr")
    with pytest.raises(FileNotFoundError, match="none.exr"):
        read_exr(tmp_path / "none.exr")
    write_exr_channels(tmp_path / "z.exr", {"Z": np.ones((3, 3), np.float32)})
    with pytest.raises(ValueError, match=r"z.exr: no R, G, B channels among \['Z'\]"):
        read_exr(tmp_path / "z.exr")
    with pytest.raises(ValueError, match="one shape"):
        write_exr_channels(tmp_path / "s.exr", {"R": np.ones((3, 3)), "G": np.ones((3, 4))})
    with pytest.raises(ValueError, match="H, W > 0"):
        write_exr_channels(tmp_path / "s.exr", {"R": np.ones((0, 3))})
    assert not (tmp_path / "s.exr").exists()


def test_png_values_modes_and_damage(tmp_path):
    from PIL import Image

    u8 = np.arange(256, dtype=np.uint8).reshape(16, 16)
    exact = u8.astype(np.float32) / np.float32(255)
    rgb = np.stack([u8, u8[::-1], u8.T], axis=-1)
    write_png(tmp_path / "rgb.png", rgb)
    assert _same_bits(read_png(tmp_path / "rgb.png"), rgb.astype(np.float32) / np.float32(255))
    Image.fromarray(u8, "L").save(tmp_path / "grey.png")
    Image.fromarray(np.dstack([rgb, u8]), "RGBA").save(tmp_path / "rgba.png")
    Image.fromarray(rgb).convert("P", palette=Image.Palette.ADAPTIVE).save(tmp_path / "pal.png")
    Image.fromarray(u8.astype(np.uint16) * 257).save(tmp_path / "grey16.png")
    assert _same_bits(read_png(tmp_path / "grey.png"), np.repeat(exact[..., None], 3, 2))
    assert _same_bits(read_png(tmp_path / "rgba.png"), rgb.astype(np.float32) / np.float32(255))
    assert read_png(tmp_path / "pal.png").shape == (16, 16, 3)
    assert _same_bits(read_png(tmp_path / "grey16.png"), np.repeat(exact[..., None], 3, 2))
    data = (tmp_path / "rgb.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="cut.png: unreadable PNG"):
        read_png(tmp_path / "cut.png")
    (tmp_path / "junk.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="junk.png"):
        read_png(tmp_path / "junk.png")


def test_png_is_read_through_safeio(tmp_path, monkeypatch):
    """A PNG is opened as safeio opens inputs: a FIFO is refused at once (Pillow would
    block on it), a file over the PNG cap before a byte is decoded; both one line naming it."""
    from noisefeat import safeio

    os.mkfifo(tmp_path / "fifo.png")
    with pytest.raises(safeio.InputFileError, match="fifo.png: PNG is a FIFO"):
        read_png(tmp_path / "fifo.png")
    write_png(tmp_path / "big.png", np.zeros((8, 8, 3), np.uint8))
    monkeypatch.setitem(safeio.CAPS, "PNG", 16)
    with pytest.raises(safeio.InputFileError, match="big.png: PNG is .* over the limit"):
        read_png(tmp_path / "big.png")
    with pytest.raises(FileNotFoundError, match="no such PNG file"):
        read_png(tmp_path / "absent.png")


def test_png_16_bit_colour_is_refused_not_silently_reduced(tmp_path):
    import struct
    import zlib

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    rows = b"".join(b"\0" + np.full((2, 3), 40000, ">u2").tobytes() for _ in range(2))
    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 2, 2, 16, 2, 0, 0, 0))
           + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))
    (tmp_path / "c16.png").write_bytes(png)
    with pytest.raises(ValueError, match="c16.png: 16-bit colour"):
        read_png(tmp_path / "c16.png")


def test_exr_and_png_io_import_no_mitsuba_and_print_nothing_on_damage(tmp_path):
    """In a fresh process: write, read, read a truncated file; Mitsuba and Dr.Jit stay
    unimported and the C libraries print nothing on stderr."""
    code = f"""
import sys, numpy as np
from pathlib import Path
from learning.data.exr import read_exr, write_exr, write_exr_channels, read_exr_channels, write_png, read_png
d = Path({str(tmp_path)!r})
write_exr(d / "a.exr", np.ones((40, 40, 3), np.float32), half=True)
write_exr_channels(d / "f.exr", {{"R": np.ones((4, 4), np.float32), "spp": np.ones((4, 4), np.float32)}})
write_png(d / "a.png", np.zeros((4, 4, 3), np.uint8))
assert read_exr(d / "a.exr").sum() == 4800 and list(read_exr_channels(d / "f.exr")) == ["R", "spp"]
assert read_png(d / "a.png").shape == (4, 4, 3)
data = (d / "a.exr").read_bytes()
for n in (10, 300, len(data) - 1):
    (d / "cut.exr").write_bytes(data[:n])
    try:
        read_exr(d / "cut.exr")
    except ValueError:
        pass
    else:
        raise SystemExit("no error")
print(sorted(m for m in ("mitsuba", "drjit", "matplotlib") if m in sys.modules))
"""
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         timeout=120, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
    assert out.stderr == ""
