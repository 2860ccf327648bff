"""The cold row of `bench native`: what a user times, a fresh process from the
command to the files written, for `noisestop render` and for the plain `mi.render` script
that renders the same XML scene to the same max spp, each broken down.

Why: the warm loop's wall is not what users see. A user times the whole command: Python's
imports, Mitsuba's variant, the scene's load, the kernels' compile, the first decisions,
and writing the outputs.
"""
from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

#: the plain script users compare against: import, variant, load, render, write, each timed
MI_SCRIPT = r"""
import json, sys, time
t0 = time.perf_counter()
import mitsuba as mi
t1 = time.perf_counter()
mi.set_variant(sys.argv[4])
t2 = time.perf_counter()
scene = mi.load_file(sys.argv[1])
t3 = time.perf_counter()
img = mi.render(scene, spp=int(sys.argv[2]))
import numpy as np
pixels = np.asarray(img)            # Dr.Jit is lazy: the render (and its compile) runs here
t4 = time.perf_counter()
mi.Bitmap(img).write(sys.argv[3])
t5 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "variant_s": t2 - t1, "load_s": t3 - t2, "render_s": t4 - t3,
                  "write_s": t5 - t4}))
"""


#: what the `noisestop` entry point runs (also where no entry point is installed: a GPU site)
NOISESTOP = "from service.cli import run; run()"


def cbox_xml(size: int) -> str:
    """Mitsuba's Cornell box (`mi.cornell_box()`) as an XML scene of `size` x `size`."""
    import mitsuba as mi

    if mi.variant() is None:
        mi.set_variant("scalar_rgb")
    d = mi.cornell_box()
    d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = int(size)
    return '<scene version="3.0.0">\n' + "".join(_xml(k, v, top=True) for k, v in d.items() if k != "type") + \
        "</scene>\n"


def _xml(name: str, value: Any, top: bool = False) -> str:
    import mitsuba as mi

    if isinstance(value, dict):
        if value.get("type") == "ref":
            return f'<ref id="{value["id"]}" name="{name}"/>\n'
        if value.get("type") == "rgb":
            return f'<rgb name="{name}" value="{",".join(str(float(x)) for x in value["value"])}"/>\n'
        tag = _tag(value["type"])
        head = f'id="{name}"' if top else f'name="{name}"'
        inner = "".join(_xml(k, v) for k, v in value.items() if k != "type")
        return f'<{tag} type="{value["type"]}" {head}>\n{inner}</{tag}>\n'
    if isinstance(value, mi.ScalarTransform4f):
        m = " ".join(f"{float(x):.9g}" for row in value.matrix for x in row)
        return f'<transform name="{name}"><matrix value="{m}"/></transform>\n'
    if isinstance(value, bool):
        return f'<boolean name="{name}" value="{str(value).lower()}"/>\n'
    if isinstance(value, int):
        return f'<integer name="{name}" value="{value}"/>\n'
    if isinstance(value, float):
        return f'<float name="{name}" value="{value!r}"/>\n'
    return f'<string name="{name}" value="{value}"/>\n'


def _tag(kind: str) -> str:
    return {"perspective": "sensor", "independent": "sampler", "hdrfilm": "film", "diffuse": "bsdf",
            "path": "integrator", "rectangle": "shape", "cube": "shape", "area": "emitter",
            "gaussian": "rfilter", "box": "rfilter"}[kind]


def cold_row(size: int = 256, max_spp: int = 1024, variant: str | None = None, repeats: int = 3) -> dict[str, Any]:
    """Fresh processes, interleaved `repeats` times: `noisestop render` (flip, default
    settings, max `max_spp`) and the plain `mi.render` script, both on the same XML, each
    from the command to the files written, with each one's breakdown. The figures are the
    medians; every run is kept (`runs`). The first pair also pays for a cold page cache and
    Dr.Jit kernel cache, as a user's first call does."""
    from learning.data.variant import select_variant

    variant = variant or select_variant()
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        xml = Path(tmp) / "cbox.xml"
        xml.write_text(cbox_xml(size))
        for _ in range(max(1, int(repeats))):
            runs.append(_cold_pair(xml, Path(tmp), max_spp, variant))
    med = {side: {k: float(np.median([r[side][k] for r in runs])) for k in runs[0][side]}
           for side in ("mi_render", "noisestop")}
    return {"variant": variant, "size": size, "max_spp": max_spp, "repeats": len(runs), **med,
            "ratio": float(np.median([r["noisestop"]["wall_s"] / r["mi_render"]["wall_s"] for r in runs])),
            "runs": runs}


def _cold_pair(xml: Path, tmp: Path, max_spp: int, variant: str) -> dict[str, Any]:
    """One run of each command (the script first), and how long the imports alone take."""
    t0 = time.perf_counter()
    mi_out = subprocess.run([sys.executable, "-c", MI_SCRIPT, str(xml), str(max_spp), str(tmp / "mi.exr"),
                             variant], capture_output=True, text=True, check=True)
    mi_wall = time.perf_counter() - t0
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", "import renderer.live.adaptive, service.cli"], check=True)
    imports = time.perf_counter() - t0
    out = tmp / "ours"
    t0 = time.perf_counter()
    ours = subprocess.run([sys.executable, "-c", NOISESTOP, "render", "--scene", str(xml),
                           "--max-spp", str(max_spp), "--out", str(out), "--json"], capture_output=True, text=True)
    ours_wall = time.perf_counter() - t0
    if ours.returncode != 0:
        raise RuntimeError(f"noisestop render failed: {ours.stderr[-500:]}")
    report = json.loads((out / "report.json").read_text())
    calls = report["render_calls"]
    return {"mi_render": {"wall_s": mi_wall, **json.loads(mi_out.stdout.strip().splitlines()[-1])},
            "noisestop": {"wall_s": ours_wall, "imports_s": imports, "report_wall_s": report["wall_s"],
                          "mean_spp": report["mean_spp"],
                          "traced_vs_spent": calls["samples_traced"] / max(1, report["samples_spent"]),
                          **{k: v for k, v in report["timing"].items() if isinstance(v, (int, float))}}}


if __name__ == "__main__":
    print(json.dumps(cold_row(), indent=1))
