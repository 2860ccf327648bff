"""The adaptive loop's state under budgets, forged checkpoints and long renders: whether a
budget that does not bind (or a resume after a time limit) gives the unbudgeted image,
whether forged decision evidence is refused, and peak memory against the number of passes.
"""
from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .cli_run import run_cli

#: the render the budget rows compare: cornell 96 px, flip at tile grain, decisions skipped
CORNELL = ["render", "--scene", "cornell", "--resolution", "96", "--max-spp", "1024", "--seed", "3"]


def _image(out: Path) -> np.ndarray:
    from learning.data.exr import read_exr

    return read_exr(out / "final.exr")


def _mean_spp(out: Path) -> float:
    return float(json.loads((out / "report.json").read_text())["mean_spp"])


def _forge(src: Path, dst: Path, change: Callable[[dict[str, np.ndarray]], None]) -> Path:
    """A copy of the out folder `src` whose checkpoint `change` edited, digest recomputed."""
    from learning.data.npz import DIGEST_KEY, read_npz, savez_bytes

    shutil.copytree(src, dst)
    arrays = {k: v for k, v in read_npz(dst / "checkpoint.npz", kind="checkpoint").items() if k != DIGEST_KEY}
    change(arrays)
    (dst / "checkpoint.npz").write_bytes(savez_bytes(arrays, with_digest=True))
    return dst


def bench_loop_state(passes: tuple[int, ...] = (500, 2500)) -> list[dict[str, Any]]:
    """Rows: budgets against the unbudgeted render (image equal, mean spp), forged decision
    evidence on resume (exit, message), and an 8x8 uniform render's peak RSS at each count
    of `passes` (step 1)."""
    from tests.support.forgery import FORGERIES

    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        plain = run_cli([*CORNELL, "--out", str(t / "plain")], timeout=300)
        ref = _image(t / "plain")
        rows.append({"case": "E7 no budget", "same_image": True, "mean_spp": _mean_spp(t / "plain"), **plain})
        for name, extra in (("E7 --time-limit 1000 (not reached)", ["--time-limit", "1000"]),
                            ("E7 --spp-budget 1000000 (above max spp)", ["--spp-budget", "1000000"])):
            out = t / f"b{len(rows)}"
            r = run_cli([*CORNELL, *extra, "--out", str(out)], timeout=300)
            rows.append({"case": name, "same_image": bool(np.array_equal(_image(out), ref)),
                         "mean_spp": _mean_spp(out), **r})
        cut = t / "cut"
        first = run_cli([*CORNELL, "--time-limit", "2", "--out", str(cut)], timeout=300)
        shutil.copytree(cut, t / "cut_kept")
        r = run_cli([*CORNELL, "--resume", "--out", str(cut)], timeout=300)
        r["seconds"] += first["seconds"]
        r["peak_rss_kib"] = max(r["peak_rss_kib"], first["peak_rss_kib"])
        rows.append({"case": "E7 --time-limit 2, then --resume", "same_image": bool(np.array_equal(_image(cut), ref)),
                     "mean_spp": _mean_spp(cut), **r})
        for name, change in FORGERIES.items():
            out = _forge(t / "cut_kept", t / f"f{len(rows)}", change)
            r = run_cli([*CORNELL, "--resume", "--out", str(out)], timeout=300)
            rows.append({"case": f"E8 {name}, --resume", "same_image": None, "mean_spp": None, **r})
        for n in passes:
            out = t / f"m{n}"
            r = run_cli(["render", "--scene", "cornell", "--resolution", "8", "--criterion", "uniform", "--step", "1",
                         "--min-spp", "1", "--max-spp", str(n), "--out", str(out)], timeout=600)
            rows.append({"case": f"E14 8x8 uniform, {n} passes", "same_image": None, "mean_spp": None, **r})
    return rows


def md_loop_state(rows: list[dict[str, Any]]) -> str:
    lines = ["| case | exit | seconds | peak RSS | image = no budget | mean spp | message |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        same = "" if r["same_image"] is None else ("yes" if r["same_image"] else "NO")
        spp = "" if r["mean_spp"] is None else f"{r['mean_spp']:.2f}"
        msg = r["message"].replace("|", "/") if r["exit"] != 0 else ""
        lines.append(f"| {r['case']} | {r['exit']} | {r['seconds']:.1f} | {r['peak_rss_kib'] / 1024:.0f} MiB | "
                     f"{same} | {spp} | {msg} |")
    return "\n".join(lines)


if __name__ == "__main__":
    print(md_loop_state(bench_loop_state()))
