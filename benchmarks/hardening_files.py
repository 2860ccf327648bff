"""Hostile files against the commands that read them (in `noisestop bench hardening`):
devices, FIFOs, huge sparse files and damaged or absurd contents in every slot a command
reads (stacks, user data, checkpoints, weights, bundles, the output lock), and every kind of
file a scene XML names.

Each case is one command in a fresh process (`cli_run.run_cli`: exit, seconds, stderr
lines, peak RSS, last line). Goal: exit 2, one line naming the file, within 5 s and 400 MiB
(500 MiB for scenes), no traceback (docs/benchmarks/reliability.md).
"""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

from .cli_run import ROOT, run_cli


def hostile_files(bundle: str) -> list[dict[str, Any]]:
    """Hostile files against the commands that read them: a stack's reference as /dev/zero,
    a 3 GB (sparse) meta.json, a level EXR whose tail is zeros, the user's flip.json huge,
    nested 100000 deep or with a negative tau, a token file of /dev/zero, a budget below one
    pass and a negative max spp (goal: exit 2, one line, no traceback)."""
    import shutil
    fixtures = ROOT / "tests" / "fixtures" / "dataset"
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)

        def stack(name: str) -> Path:
            d = tmp_path / name / "data"
            shutil.copytree(fixtures, d)
            return d

        d = stack("devzero")
        (d / "checker" / "reference.exr").unlink(missing_ok=True)
        (d / "checker" / "reference.exr").symlink_to("/dev/zero")
        rows.append({"case": "reference.exr -> /dev/zero: evaluate", **run_cli(["evaluate", "--data", str(d)])})
        rows.append({"case": "reference.exr -> /dev/zero: dataset check",
                     **run_cli(["dataset", "check", str(d)])})
        d = stack("bigmeta")
        with open(d / "checker" / "meta.json", "r+b") as f:
            f.truncate(3 << 30)                                   # sparse: no disk used
        rows.append({"case": "meta.json of 3 GB (sparse): evaluate", **run_cli(["evaluate", "--data", str(d)])})
        rows.append({"case": "meta.json of 3 GB (sparse): dataset check", **run_cli(["dataset", "check", str(d)])})
        d = stack("zerotail")
        level = sorted((d / "checker" / "levels").glob("*.exr"))[0]
        data = bytearray(level.read_bytes())
        data[len(data) // 2:] = bytes(len(data) - len(data) // 2)
        level.write_bytes(bytes(data))
        rows.append({"case": "level EXR, zero-filled tail, same size: evaluate",
                     **run_cli(["evaluate", "--data", str(d)])})
        rows.append({"case": "level EXR, zero-filled tail, same size: dataset check",
                     **run_cli(["dataset", "check", str(d)])})
        home = tmp_path / "home"
        (home / "noisestop").mkdir(parents=True)
        user_flip = home / "noisestop" / "flip.json"
        with open(user_flip, "wb") as f:
            f.truncate(3 << 30)
        render = ["render", "--scene", "cornell", "--resolution", "64", "--max-spp", "32", "--criterion", "flip"]
        user = {"NOISESTOP_DATA_DIR": str(home / "noisestop")}
        rows.append({"case": "user flip.json of 3 GB (sparse): render",
                     **run_cli([*render, "--out", str(tmp_path / "r1")], user)})
        user_flip.unlink()
        user_flip.write_text("[" * 100000 + "]" * 100000)
        rows.append({"case": "user flip.json nested 100000 deep: render",
                     **run_cli([*render, "--out", str(tmp_path / "r2")], user)})
        user_flip.write_text(json.dumps({"pooling": "tile8-max", "curve": [{"tau": -0.01, "c": 0.1},
                                                                          {"tau": 0.02, "c": 0.2}]}))
        rows.append({"case": "user flip.json with a negative tau: render",
                     **run_cli([*render, "--out", str(tmp_path / "r3")], user)})
        rows.append({"case": "NOISESTOP_TOKEN_FILE=/dev/zero: serve",
                     **run_cli(["serve", "--model", bundle, "--port", "0"], {"NOISESTOP_TOKEN_FILE": "/dev/zero"})})
        rows.append({"case": "render --spp-budget 8 (step 16)",
                     **run_cli([*render, "--spp-budget", "8", "--out", str(tmp_path / "r4")])})
        rows.append({"case": "render --max-spp -1",
                     **run_cli([*render, "--max-spp", "-1", "--out", str(tmp_path / "r5")])})
    return rows


def md_hostile_files(rows: list[dict[str, Any]]) -> str:
    lines = ["| hostile input | exit | seconds | stderr lines | peak RSS | message |", "|---|---|---|---|---|---|"]
    for f in rows:
        lines.append(f"| {f['case']} | {f['exit']} | {f['seconds']:.1f} | {f['lines']} | "
                     f"{f['peak_rss_kib'] / 1024:.0f} MiB | {f['message'].replace('|', '/')} |")
    return "\n".join(lines)


def input_slot_files(bundle: str) -> list[dict[str, Any]]:
    """Each input slot (a checkpoint, the feature weights, a bundle's members, the output
    lock) as /dev/zero, a FIFO and a 3 GB sparse file, against the command that reads it
    (goal: exit 2, one line naming the file, at most 5 s and 400 MiB)."""
    import shutil

    rows = []
    render = ["render", "--scene", "cornell", "--resolution", "32", "--max-spp", "16", "--criterion", "variance"]
    evaluate = ["evaluate", "--data", str(ROOT / "tests" / "fixtures" / "dataset"), "--criterion", "model"]
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)

        def bad(path: Path, kind: str) -> Path:
            path.parent.mkdir(parents=True, exist_ok=True)
            if kind == "/dev/zero":
                path.symlink_to("/dev/zero")
            elif kind == "FIFO":
                os.mkfifo(path)
            else:
                with open(path, "wb") as f:
                    f.truncate(3 << 30)
            return path

        for i, kind in enumerate(("/dev/zero", "FIFO", "3 GB sparse")):
            out = tmp_path / f"ck{i}"
            bad(out / "checkpoint.npz", kind)
            rows.append({"case": f"checkpoint.npz as {kind}: render --resume",
                         **run_cli([*render, "--resume", "--out", str(out)])})
            weights = bad(tmp_path / f"w{i}" / "weights.safetensors", kind)
            rows.append({"case": f"NOISESTOP_FEATURE_WEIGHTS as {kind}: evaluate --criterion model",
                         **run_cli([*evaluate, "--model", bundle], {"NOISESTOP_FEATURE_WEIGHTS": str(weights)})})
            for member in ("model.skops", "manifest.json"):
                b = tmp_path / f"b{i}{member}"
                shutil.copytree(bundle, b)
                (b / member).unlink()
                bad(b / member, kind)
                rows.append({"case": f"bundle {member} as {kind}: evaluate --criterion model",
                             **run_cli([*evaluate, "--model", str(b)])})
            if kind != "3 GB sparse":             # a lock file's content is never read past 200 bytes
                out = tmp_path / f"lk{i}"
                bad(out / ".noisestop.lock", kind)
                rows.append({"case": f"output lock file as {kind}: render", **run_cli([*render, "--out", str(out)])})
    return rows


#: an element of a scene XML naming the file NAME, by the kind of file it names
SCENE_NAMING = {
    "mesh (ply)": '<shape type="ply"><string name="filename" value="{name}"/></shape>',
    "include": '<include filename="{name}"/>',
    "bitmap texture": ('<shape type="sphere"><bsdf type="diffuse"><texture type="bitmap" name="reflectance">'
                       '<string name="filename" value="{name}"/></texture></bsdf></shape>'),
    "environment map": '<emitter type="envmap"><string name="filename" value="{name}"/></emitter>',
}


def bench_scene_files() -> list[dict[str, Any]]:
    """Files a scene names: each kind a scene XML names (mesh, include, bitmap,
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
