"""Non-finite scenes (in `noisestop bench hardening`): emitters of NaN, Inf or 1e38 and a
sphere of NaN reflectance, rendered by each criterion. A unit holding a pixel without a
finite sample must never be called converged, and the render's end must say so (exit 3, a
warning line, the report's `nonfinite` counts; docs/benchmarks/reliability.md).
"""
from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

from .cli_run import run_cli


#: the scenes: (name, constant emitter radiance, sphere reflectance)
NONFINITE_SCENES = (("NaN emitter", "nan", None), ("Inf emitter", "inf", None), ("1e38 emitter", "1e38", None),
                    ("NaN reflectance sphere", "0.5", "nan"))


def bench_nonfinite_scenes(criteria: tuple[str, ...] = ("flip", "model", "variance")) -> list[dict[str, Any]]:
    """The scenes rendered 32x32 (16-px blocks, 4..16 spp) by each criterion: units
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
             "pixel (never converged) | pixels without a finite sample | exit | stderr warning lines |",
             "|---|---|---|---|---|---|---|"]
    for x in rows:
        lines.append(f"| {x['scene']} | {x['criterion']} | {x['converged']} of {x['units']} | {x['held_units']} | "
                     f"{x['pixels_without_sample']} | {x['exit']} | {x['warning_lines']} |")
    return "\n".join(lines)
