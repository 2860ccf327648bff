"""Scene XMLs that would make Mitsuba open, load or run what the scene walker
(`renderer.scenes.scenefiles`) must stop (in `noisestop bench hardening`), each as a user
meets it: `noisestop render --scene FILE.xml` in a fresh process (exit, seconds, peak RSS,
the last stderr line), or the Python call for the API cases. Goal: each refused in one line
(exit 2, a ValueError from the API) within 5 s and 500 MiB, a planted library's code never
run.
"""
from __future__ import annotations

import os
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import zlib
from pathlib import Path
from typing import Any, Callable

from .cli_run import ROOT, run_cli

SENSOR = ('<sensor type="perspective"><film type="hdrfilm"><integer name="width" value="16"/>'
          '<integer name="height" value="16"/></film></sensor>')
RENDER = ["--max-spp", "16", "--criterion", "uniform"]


def _scene(folder: Path, body: str, head: bytes = b"", name: str = "scene.xml") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    path.write_bytes(head + f'<scene version="3.0.0">{body}{SENSOR}</scene>'.encode())
    return path


def _mesh(name: str, kind: str = "ply") -> str:
    return f'<shape type="{kind}"><string name="filename" value="{name}"/></shape>'


def _bomb_png(path: Path, side: int = 20000) -> None:
    """A real RGB PNG of side x side black pixels: about 1.2 MB for 20000 (1.2 GB decoded)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    deflate, row, parts = zlib.compressobj(9), bytes(1 + 3 * side), []
    for _ in range(side // 100):
        parts.append(deflate.compress(row * 100))
    parts.append(deflate.flush())
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", side, side, 8, 2, 0, 0, 0))
                     + chunk(b"IDAT", b"".join(parts)) + chunk(b"IEND", b""))


def _nested(n: int) -> str:
    bsdf = '<bsdf type="diffuse"/>'
    for _ in range(n):
        bsdf = f'<bsdf type="twosided">{bsdf}</bsdf>'
    return f'<shape type="sphere">{bsdf}</shape>'


def run_python(code: str, timeout: float = 60.0) -> dict[str, Any]:
    """`code` in a fresh process, as `run_cli` runs a command: exit, seconds, peak RSS, and
    the last stderr line (the snippet prints an exception as "Type: message", exit 2)."""
    script = ("import sys\ntry:\n" + "".join(f"    {line}\n" for line in code.splitlines())
              + "except Exception as exc:\n    print(f'{type(exc).__name__}: {exc}', file=sys.stderr)\n"
                "    sys.exit(2)\n")
    wrapper = ("import resource, subprocess, sys; r = subprocess.run(sys.argv[1:]); "
               "print('PEAK_RSS_KIB', resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, file=sys.stderr); "
               "sys.exit(r.returncode)")
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-c", wrapper, sys.executable, "-c", script], cwd=ROOT,
                          env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True,
                          timeout=timeout)
    err = proc.stderr.splitlines()
    peak = [int(x.split()[1]) for x in err if x.startswith("PEAK_RSS_KIB ")]
    lines = [x for x in err if x.strip() and not x.startswith("PEAK_RSS_KIB ")]
    return {"exit": proc.returncode, "seconds": time.monotonic() - t0, "lines": len(lines),
            "message": lines[-1][:200] if lines else "", "peak_rss_kib": peak[0] if peak else 0}


def _render(xml: Path, out: Path) -> dict[str, Any]:
    return run_cli(["-q", "render", "--scene", str(xml), *RENDER, "--out", str(out)])


def _e1(d: Path) -> dict[str, Any]:
    (d / "mÃ©.ply").parent.mkdir(parents=True, exist_ok=True)
    (d / "mÃ©.ply").write_bytes(b"ply\n")
    os.mkfifo(d / "mé.ply")
    return _render(_scene(d, _mesh("mé.ply"), b'<?xml version="1.0" encoding="windows-1252"?>'), d / "out")


def _e2(d: Path) -> dict[str, Any]:
    d.mkdir(parents=True)
    (d / "a b.ply").write_bytes(b"ply\n")
    os.mkfifo(d / "a  b.ply")
    head = b"<!DOCTYPE scene [<!ATTLIST string value NMTOKENS #IMPLIED>]>"
    return _render(_scene(d, _mesh("a  b.ply"), head), d / "out")


def _e3(d: Path) -> dict[str, Any]:
    (d / "other" / "sub").mkdir(parents=True)
    (d / "scene").mkdir()
    (d / "scene" / "L").symlink_to(d / "other" / "sub")
    _scene(d / "other", '<include filename="evil.xml"/>', name="inc.xml")
    os.mkfifo(d / "other" / "evil.xml")
    _scene(d / "scene", "", name="inc.xml")
    _scene(d / "scene", "", name="evil.xml")
    return _render(_scene(d / "scene", '<include filename="L/../inc.xml"/>'), d / "out")


def _e4(d: Path) -> dict[str, Any]:
    marker = d / "marker"
    (d / "plugins").mkdir(parents=True)
    (d / "lib.c").write_text('#include <stdio.h>\n__attribute__((constructor)) static void ran(void) {\n'
                             f'  FILE *f = fopen("{marker}", "w"); if (f) {{ fputs("ran", f); fclose(f); }}\n}}\n')
    subprocess.run(["gcc", "-shared", "-fPIC", "-o", str(d / "plugins" / "diffuse.so"), str(d / "lib.c")],
                   check=True, capture_output=True, timeout=120)
    r = _render(_scene(d, '<shape type="sphere"><bsdf type="diffuse"/></shape>'), d / "out")
    return {**r, "note": "planted code ran" if marker.exists() else "planted code never ran"}


def _e5_png(element: str) -> Callable[[Path], dict[str, Any]]:
    def case(d: Path) -> dict[str, Any]:
        d.mkdir(parents=True)
        _bomb_png(d / "big.png")
        body = ('<shape type="sphere"><bsdf type="diffuse"><texture type="bitmap" name="reflectance">'
                '<string name="filename" value="big.png"/></texture></bsdf></shape>' if element == "bitmap"
                else '<emitter type="envmap"><string name="filename" value="big.png"/></emitter>')
        r = _render(_scene(d, body), d / "out")
        return {**r, "note": f"file {(d / 'big.png').stat().st_size / 1e6:.1f} MB"}
    return case


def _e5_obj(d: Path) -> dict[str, Any]:
    d.mkdir(parents=True)
    with open(d / "m.obj", "wb") as f:
        f.write(b"v 0 0 0\n")
        f.truncate((2 << 30) - 1)
    return _render(_scene(d, _mesh("m.obj", "obj")), d / "out")


def _e5_ply(d: Path) -> dict[str, Any]:
    d.mkdir(parents=True)
    (d / "m.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000\n"
                              b"property float x\nproperty float y\nproperty float z\nend_header\n" + bytes(36))
    return _render(_scene(d, _mesh("m.ply")), d / "out")


def _e6(n: int) -> Callable[[Path], dict[str, Any]]:
    return lambda d: _render(_scene(d, _nested(n)), d / "out")


def _e9(d: Path) -> dict[str, Any]:
    body = ('<integrator type="noisestop"><integrator type="noisestop"><integrator type="path"/></integrator>'
            '</integrator><shape type="sphere"/>')
    return run_cli(["-q", "render", "--scene", str(_scene(d, body)), "--out", str(d / "out")])


def _e15(includes: int) -> Callable[[Path], dict[str, Any]]:
    def case(d: Path) -> dict[str, Any]:
        d.mkdir(parents=True)
        (d / "big.xml").write_text('<scene version="3.0.0"><!--' + "x" * (1 << 20) + "--></scene>")
        xml = _scene(d, '<include filename="big.xml"/>' * includes)
        if includes < 1024:            # under the bytes bound: the walker's own time, in process
            from renderer.scenes.scenefiles import check_scene_files

            t0 = time.monotonic()
            check_scene_files(xml)
            return {"exit": 0, "seconds": time.monotonic() - t0, "lines": 0, "peak_rss_kib": 0,
                    "message": "", "note": "the walker alone, in process (passes)"}
        return _render(xml, d / "out")
    return case


def _d13(d: Path) -> dict[str, Any]:
    xml = _scene(d, '<integrator type="noisestop"><integrator type="path"/></integrator><shape type="sphere"/>')
    return run_python(f"import renderer, mitsuba as mi\nrenderer.register()\nscene = mi.load_file({str(xml)!r})\n"
                      "scene.integrator().render(scene, sensor=5)")


#: id, what, how it is made and run
CASES: tuple[tuple[str, str, Callable[[Path], dict[str, Any]]], ...] = (
    ("E1", "windows-1252 declared, UTF-8 name of a FIFO", _e1),
    ("E2", "DOCTYPE with an NMTOKENS ATTLIST, name of a FIFO", _e2),
    ("E3", "include L/../inc.xml through a link, then a FIFO", _e3),
    ("E4", "plugins/diffuse.so (gcc) beside the scene", _e4),
    ("E5", "20000 x 20000 PNG bitmap texture", _e5_png("bitmap")),
    ("E5", "20000 x 20000 PNG envmap", _e5_png("envmap")),
    ("E5", "sparse obj just under the 2 GiB mesh cap", _e5_obj),
    ("E5", "ply stating 10^9 vertices in 200 bytes", _e5_ply),
    ("E6", "40 nested twosided BSDFs", _e6(40)),
    ("E6", "20,000 nested twosided BSDFs", _e6(20_000)),
    ("E9", "noisestop nested in noisestop", _e9),
    ("E15", "4,000 includes of a 1 MB file", _e15(4000)),
    ("E15", "500 includes of a 1 MB file", _e15(500)),
    ("D13", "integrator.render(scene, sensor=5) (API)", _d13),
)


def bench_scene_walk() -> list[dict[str, Any]]:
    """Each case of `CASES` in a fresh folder: exit, seconds, peak RSS, the message."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, (case, what, run) in enumerate(CASES):
            if run is _e4 and shutil.which("gcc") is None:
                rows.append({"case": case, "what": what, "exit": "skipped", "seconds": 0.0, "peak_rss_kib": 0,
                             "lines": 0, "message": "gcc is not installed"})
                continue
            rows.append({"case": case, "what": what, **run(Path(tmp) / f"c{i}")})
    return rows


def md_scene_walk(rows: list[dict[str, Any]]) -> str:
    lines = ["| case | what | exit | seconds | stderr lines | peak RSS | message |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        note = f" ({r['note']})" if r.get("note") else ""
        rss = f"{r['peak_rss_kib'] / 1024:.0f} MiB" if r["peak_rss_kib"] else "-"
        lines.append(f"| {r['case']} | {r['what']} | {r['exit']} | {r['seconds']:.1f} | {r['lines']} | {rss} | "
                     f"{r['message'].replace('|', '/')}{note} |")
    return "\n".join(lines)


if __name__ == "__main__":
    print(md_scene_walk(bench_scene_walk()))
