"""Hardening, fifth round (issue 51): files a scene XML names, non-finite scenes, and JSON
bodies at the parse pool's threshold (docs/benchmarks/reliability.md).
"""
from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

from .cli_run import run_cli


#: an element of a scene XML naming the file NAME, by the kind of file it names
SCENE_NAMING = {
    "mesh (ply)": '<shape type="ply"><string name="filename" value="{name}"/></shape>',
    "include": '<include filename="{name}"/>',
    "bitmap texture": ('<shape type="sphere"><bsdf type="diffuse"><texture type="bitmap" name="reflectance">'
                       '<string name="filename" value="{name}"/></texture></bsdf></shape>'),
    "environment map": '<emitter type="envmap"><string name="filename" value="{name}"/></emitter>',
}


def bench_scene_files() -> list[dict[str, Any]]:
    """Issue 51's scene-named files: each kind a scene XML names (mesh, include, bitmap,
    environment map) as /dev/zero, a FIFO, a 3 GB sparse file and a missing file, against
    `render --scene FILE.xml` (goal: exit 2, one line naming the file, at most 5 s and 500 MiB)."""
    from tests.support.bad_files import BAD_KINDS, bad_file

    sensor = ('<sensor type="perspective"><film type="hdrfilm"><integer name="width" value="16"/>'
              '<integer name="height" value="16"/></film></sensor>')
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, (element, naming) in enumerate(SCENE_NAMING.items()):
            for j, kind in enumerate(BAD_KINDS):
                d = Path(tmp) / f"s{i}{j}"
                d.mkdir()
                target = bad_file(d / "named.dat", kind)
                xml = d / "scene.xml"
                xml.write_text(f'<scene version="3.0.0">{naming.format(name=target.name)}{sensor}</scene>')
                r = run_cli(["render", "--scene", str(xml), "--max-spp", "16", "--criterion", "uniform",
                              "--out", str(d / "out")])
                rows.append({"case": f"{element} as {kind}: render", "names_file": str(target.name) in r["message"],
                             **r})
    return rows


def md_scene_files(rows: list[dict[str, Any]]) -> str:
    lines = ["| scene names | exit | seconds | stderr lines | peak RSS | names the file | message |",
             "|---|---|---|---|---|---|---|"]
    for f in rows:
        lines.append(f"| {f['case']} | {f['exit']} | {f['seconds']:.1f} | {f['lines']} | "
                     f"{f['peak_rss_kib'] / 1024:.0f} MiB | {'yes' if f['names_file'] else 'NO'} | "
                     f"{f['message'].replace('|', '/')} |")
    return "\n".join(lines)


#: the non-finite scenes of issue 51: (name, constant emitter radiance, sphere reflectance)
NONFINITE_SCENES = (("NaN emitter", "nan", None), ("Inf emitter", "inf", None), ("1e38 emitter", "1e38", None),
                    ("NaN reflectance sphere", "0.5", "nan"))


def bench_nonfinite_scenes(criteria: tuple[str, ...] = ("flip", "model", "variance")) -> list[dict[str, Any]]:
    """Issue 51's scenes rendered 32x32 (16-px blocks, 4..16 spp) by each criterion: units
    converged (goal: 0 among those with pixels without a finite sample), exit status
    (3: finished with such pixels), and whether the end says so (stderr and summary)."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, radiance, reflectance in NONFINITE_SCENES:
            scene = Path(tmp) / f"{len(rows)}.xml"
            sphere = "" if reflectance is None else (
                '<shape type="sphere"><float name="radius" value="0.7"/><bsdf type="diffuse">'
                f'<rgb name="reflectance" value="{reflectance}, {reflectance}, {reflectance}"/></bsdf></shape>')
            scene.write_text(
                '<scene version="3.0.0"><integrator type="path"/><sensor type="perspective"><float name="fov" '
                'value="40"/><transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/>'
                '</transform><film type="hdrfilm"><integer name="width" value="32"/><integer name="height" '
                f'value="32"/></film></sensor><emitter type="constant"><rgb name="radiance" value="{radiance}, '
                f'{radiance}, {radiance}"/></emitter>{sphere}</scene>')
            for criterion in criteria:
                out = Path(tmp) / f"out{len(rows)}"
                run = run_cli(["render", "--scene", str(scene), "--out", str(out), "--block", "16", "--step", "4",
                                "--min-spp", "4", "--max-spp", "16", "--criterion", criterion])
                rep = json.loads((out / "report.json").read_text()) if (out / "report.json").exists() else {}
                nf = rep.get("nonfinite", {})
                units = rep.get("tiles", rep.get("blocks", []))
                rows.append({"scene": name, "criterion": criterion, "exit": run["exit"], "seconds": run["seconds"],
                             "units": len(units), "converged": sum(u["converged"] for u in units),
                             "held_units": nf.get("units"), "pixels_without_sample": nf.get("pixels"),
                             "dropped": nf.get("dropped"), "warning_lines": run["stderr_nonfinite"],
                             "tracebacks": run["tracebacks"]})
    return rows


def md_nonfinite(rows: list[dict[str, Any]]) -> str:
    lines = ["| scene (32x32, 16-px blocks, 4..16 spp) | criterion | units converged | units without a finite "
             "pixel (never converged) | pixels without a finite sample | exit | stderr warning lines |", "|---|---|---|---|---|---|---|"]
    for x in rows:
        lines.append(f"| {x['scene']} | {x['criterion']} | {x['converged']} of {x['units']} | {x['held_units']} | "
                     f"{x['pixels_without_sample']} | {x['exit']} | {x['warning_lines']} |")
    return "\n".join(lines)


def bench_inline_json(bundle: str, seconds: float = 8.0, clients: tuple[int, ...] = (1, 4)) -> list[dict[str, Any]]:
    """Issue 51's bodies at the parse pool's threshold (16 KiB) looped against a fresh server:
    16.3 kB nested 11 deep (was parsed on the server's own thread), the same at 16.5 kB
    (in the pool before too), the costliest body still parsed inline (`attack.bound_json`)
    and a valid 16 kB halves request, by 1 and by 4 clients; normal
    p99 against alone and health p95 (goals: at most 2x, at most 100 ms)."""
    from functools import partial

    from . import attack
    from .loadtest import LocalServer, make_request
    rows = []
    halves = partial(make_request, blocks=16, size=128, binary=True, inputs="halves")
    for name, body, models, normal in (
            ("16.3 kB nested 11 deep", partial(attack.nested_json, 16_300), {"demo": bundle}, None),
            ("16.5 kB nested 11 deep", partial(attack.nested_json, 16_500), {"demo": bundle}, None),
            ("16 kB at the inline bound (253 lists)", partial(attack.bound_json, 16_300), {"demo": bundle}, None),
            ("valid 16 kB halves", partial(attack.valid_halves_json, 16_000), {"bundled": None}, halves)):
        for n in clients:           # the halves body, and the normal requests beside it, to the bundled model
            with LocalServer(models) as s:
                r = attack.costly_json_loop(s.url, s.token, seconds=seconds, attack=body, attackers=n, make=normal)
                r["tracebacks"] = s.log().count("Traceback")
            rows.append({"body": name, "clients": n, **r})
    return rows


def md_inline_json(rows: list[dict[str, Any]]) -> str:
    lines = ["| body | clients | answered | normal p99 alone -> loaded | ratio | health p95 |", "|---|---|---|---|---|---|"]
    for x in rows:
        lines.append(f"| {x['body']} ({x['body_bytes']} B) | {x['clients']} | {', '.join(x['attacker_statuses'])} | "
                     f"{x['alone_p99_ms']:.0f} -> {x['loaded_p99_ms']:.0f} ms | {x['p99_ratio']:.2f}x | "
                     f"{x['health_p95_ms']:.0f} ms |")
    return "\n".join(lines)
