"""`noisestop bench models dataset inputs ablation knobs`: model comparisons on held-out scenes,
their cost next to their accuracy, the dataset build's figures and the feature ablation.
"""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

from noisefeat.atomic import atomic_write
from typing import Any
import torch
from .timing import median_s


log = logging.getLogger(__name__)


def bench_models(data: str, out_dir: Path, arches: tuple[str, ...] | None = None,
                 kinds: tuple[str, ...] | None = None, quick: str = "albedo",
                 plots_dir: str = "docs", heldout: str | None = None) -> dict[str, Any]:
    """The model comparison on held-out scenes; saved as OUT/models-QUICK.json (with each
    model's offset curve) so that `bench tradeoff` draws every model without retraining."""
    import json

    from learning.training.compare import TRANSFER_ARCHES, compare_models
    from learning.training.train import SVM_KINDS
    result = compare_models(data, plots_dir, arches=TRANSFER_ARCHES if arches is None else arches,
                            kinds=SVM_KINDS if kinds is None else kinds, quick=quick, heldout=heldout)
    result.pop("fitted")
    result.update(quick=quick, data=str(data), fingerprint=_fingerprints(data, heldout))
    atomic_write(Path(out_dir) / f"models-{quick}.json", json.dumps(result, default=float))
    return result


def _fingerprints(data: str, heldout: str | None) -> str:
    from learning.data.dataset_dir import dataset_fingerprint
    return dataset_fingerprint(data) + ("" if heldout is None else "+" + dataset_fingerprint(heldout))


def saved_comparisons(data: str, out_dir: Path, heldout: str | None = None) -> list[dict[str, Any]]:
    """The model comparisons `bench models` saved in out_dir for these very datasets."""
    import json

    fp = _fingerprints(data, heldout)
    found = []
    for path in sorted(Path(out_dir).glob("models-*.json")):
        r = json.loads(path.read_text())
        if r.get("fingerprint") != fp:
            log.warning("%s: measured on another dataset; ignored", path)
            continue
        found.append(r)
    return found


def md_models(m: dict[str, Any]) -> str:
    from learning.training.compare import markdown_table
    conv = ", ".join((m.get("groups") or {}).get("converging") or []) or "none"
    text = (f"Quick image: {m['quick']}. Trained on {', '.join(m['train_scenes'])}; evaluated on the "
            f"held-out {', '.join(m['test_scenes'])} (converging inside their stacks: {conv}). Offset 0 "
            "(the hyperplane), through the stop rule.\n\n" + markdown_table(m["rows"]))
    if m.get("curves"):
        text += f"\n\nHeld-out precision against labels queried (active kinds): ![learning curves]({m['curves']})"
    return text


def md_cost_accuracy(comparisons: list[dict[str, Any]], out_png: str = "docs/cost-accuracy.png") -> str:
    """One chart of every compared model: test time per 101 sub-images against precision."""
    from learning.evaluation.plots import plot_cost_accuracy

    def label(row: dict, quick: str) -> str:      # only feature models use the quick image
        return f"{row['model']} ({quick})" if str(row["model"]).startswith("dsvm") else row["model"]
    rows = [{**r, "model": label(r, c["quick"])} for c in comparisons for r in c["rows"]]
    png = plot_cost_accuracy(rows, out_png, "decision cost vs precision on held-out scenes "
                             "(feature SVMs: quick image in brackets; * untrained conv base)")
    lines = [f"![cost vs accuracy]({png})", "", "| model | precision | test, 101 sub-images (s) |", "|---|---|---|"]
    for r in sorted((r for r in rows if r.get("test_101_s")), key=lambda r: r["test_101_s"]):
        lines.append(f"| {r['model']} | {r['precision']:.3f} | {r['test_101_s']:.4f} |")
    return "\n".join(lines)


def bench_ablation(data: str, heldout: str | None = None, out_png: str = "docs/ablation.png") -> dict[str, Any]:
    """DSVM on held-out scenes with parts of the feature pipeline switched: quick image
    (albedo / direct lighting / none, with its render time once per frame), conv weights
    (smoothing / pre-trained), wavelet layer (on / off: its two features dropped).
    Accuracy next to the cost of classifying 101 sub-images."""
    from learning.models.bundle import Model
    from learning.evaluation.evaluate import evaluate_model, time_101_sub_images
    from learning.evaluation.generalisation import split_tables
    from learning.inputs.table import QUICK_MODES
    from learning.training.train import train_model
    from noisefeat import FeatureBase

    rows = []
    wavelet_cols = [12, 25]                     # mean_13, std_13: the wavelet layer
    keep_no_wavelet = [i for i in range(26) if i not in wavelet_cols]
    quick_s = quick_image_cost()
    for weights in ("smoothing", "pretrained"):
        base = FeatureBase(weights).eval()
        for quick in (q for q in QUICK_MODES if q != "halves"):   # the paper's quick images: 26 features each
            train, test = split_tables(data, heldout, base=base, quick=quick)
            for wavelet in (True, False):
                t, h = (train, test) if wavelet else (dataclasses.replace(train, X=train.X[:, keep_no_wavelet]),
                                                      dataclasses.replace(test, X=test.X[:, keep_no_wavelet]))
                est, _ = train_model("dsvm", data, table=t, test_scenes=[], quick=quick, progress=False)
                model = Model(est, {"kind": "dsvm", "input": "features", "quick": quick})
                m = evaluate_model(model, h)
                block = tuple(next(iter(t.stacks.values())).block)
                if wavelet:
                    cost = on_cost = time_101_sub_images(model, block)
                else:   # the same pipeline without the wavelet layer's own (measured) time
                    cost = on_cost - wavelet_layer_s(block)
                rows.append({"weights": weights, "quick": quick, "wavelet": wavelet,
                             **{k: m[k] for k in ("precision", "f1", "early_stop_rate",
                                                  "spp_ratio_vs_oracle")}, "test_101_s": cost,
                             "quick_render_s": quick_s.get(quick, 0.0)})
    from . import charts
    return {"rows": rows, "quick_scene": QUICK_COST_SCENE, "plot": charts.ablation(rows, out_png)}


def md_ablation(r: dict[str, Any]) -> str:
    scene, res, spp = r["quick_scene"]
    lines = [f"![feature-pipeline ablation]({r['plot']})", "",
             "| conv weights | quick image | wavelet layer | precision | f1 | early_stop_rate "
             f"| samples / oracle | 101 sub-images (s; off: less the wavelet layer's time) "
             f"| quick image, {scene} {res}x{res} {spp} spp (s) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for x in r["rows"]:
        cost = f"{x['test_101_s']:.4f}"
        lines.append(f"| {x['weights']} | {x['quick']} | {'on' if x['wavelet'] else 'off'} | "
                     f"{x['precision']:.3f} | {x['f1']:.3f} | {x['early_stop_rate']:.3f} | "
                     f"{x['spp_ratio_vs_oracle']:.3f} | {cost} | {x['quick_render_s']:.3f} |")
    return "\n".join(lines)


QUICK_COST_SCENE = ("cornell", 256, 16)      # scene, resolution, quick spp


def wavelet_layer_s(block: tuple[int, int], n: int = 101, repeats: int = 20) -> float:
    """Seconds the feature base spends in its wavelet layer for n blocks (what switching the
    layer off would save): the layer timed alone on the spectrum forward has computed."""
    from noisefeat import FeatureBase
    base = FeatureBase().eval()
    xs = torch.rand(n, *block, generator=torch.Generator().manual_seed(0))
    with torch.inference_mode():
        mu = xs.mean(dim=(-2, -1), keepdim=True)
        spec = torch.fft.rfft2(xs - mu)
        ops = base._operators(*block)
        if "analysis12" in ops:
            return median_s(lambda: base._wavelet_even(spec, ops, mu.reshape(n)), repeats)
        return median_s(lambda: base._wavelet_odd(xs, spec, ops, mu.reshape(n)), repeats)


def quick_image_cost() -> dict[str, float]:
    """Wall time of one warm quick image per kind (once per render, full frame)."""
    from renderer.live.blocks import QUICK_KINDS, BlockRenderer
    from renderer.scenes.catalog import load_scene
    scene, res, spp = QUICK_COST_SCENE
    br = BlockRenderer(load_scene(scene, res), grid=(4, 4))
    out = {}
    for kind in QUICK_KINDS:
        br.quick_image(spp, kind=kind)                       # compile
        out[kind] = median_s(lambda k=kind: br.quick_image(spp, kind=k), 3)
    return out


def bench_knobs(data: str, heldout: str | None = None) -> dict[str, Any]:
    """Training's speed knobs (CV cap, active-learning batch) with their accuracy cost."""
    from learning.training.knobs import measure_knobs
    return measure_knobs(data, heldout)


def md_knobs(r: dict[str, Any]) -> str:
    lines = [f"Quick image {r['quick']}; held-out scenes; * = the default.", "",
             "| knob | model | setting | training (s) | precision | f1 | early_stop_rate | samples / oracle "
             "| C, gamma chosen |", "|---|---|---|---|---|---|---|---|---|"]
    for x in r["rows"]:
        setting = f"{x['value']}{' *' if x['default'] else ''}"
        if x["knob"].startswith("cross") and x.get("cv_rows"):
            setting += f" ({x['cv_rows']:,} rows)"
        lines.append(f"| {x['knob']} | {x['kind']} | {setting} | {x['seconds']:.1f} | {x['precision']:.3f} "
                     f"| {x['f1']:.3f} | {x['early_stop_rate']:.3f} | {x['spp_ratio_vs_oracle']:.3f} "
                     f"| {x['C']:g}, {x['gamma']:.3g} |")
    return "\n".join(lines)


def bench_inputs(data: str, heldout: str | None = None) -> dict[str, Any]:
    """Every composition of the half-buffer input, and the paper's quick inputs, on held-out scenes."""
    from learning.training.compare_inputs import compare_inputs
    if not heldout:
        raise ValueError("bench inputs needs --heldout DIR (scenes no composition was chosen on)")
    return compare_inputs(data, heldout)


def md_inputs(r: dict[str, Any]) -> str:
    from learning.training.compare_inputs import md_inputs as md
    return md(r)


def bench_dataset(data: str, heldout: str | None = None) -> dict[str, Any]:
    """The dataset's build time, from its build log: the latest run that rendered anything."""
    from renderer.dataset.build import BUILD_LOG, read_build_log
    out = {}
    for name, where in (("training", data), ("heldout", heldout)):
        if where is None:
            continue
        runs = [r for r in read_build_log(where) if any(not s.get("already_built") for s in r["scenes"])]
        if not runs:
            raise ValueError(f"{where}: no build run on record ({BUILD_LOG}); build it with `make dataset` "
                             "or `make heldout`")
        out[name] = runs[-1]
    return out


def md_dataset(runs: dict[str, Any]) -> str:
    titles = {"training": "Training scenes (`make dataset`)", "heldout": "Held-out scenes (`make heldout`)"}
    return "\n\n".join(f"{titles[name]}: {_md_build(r)}" for name, r in runs.items())


def _md_build(r: dict[str, Any]) -> str:
    st = r["settings"]
    resumed = [x["scene"] for x in r["scenes"] if x.get("resumed") and not x.get("already_built")]
    done = [x["scene"] for x in r["scenes"] if x.get("already_built")]
    minutes, seconds = divmod(round(r["wall_s"]), 60)
    where = (f"scheduler {r['scheduler']}" if r.get("scheduler") else
             f"{r['workers']} local workers" if r.get("workers") else "one local worker per core")
    lines = [f"{len(r['scenes'])} scenes at {st['resolution']}x{st['resolution']}, step {st['step']}, "
             f"{st['levels']} levels, reference {st['reference_spp']} spp, {where}, "
             f"{r.get('cpus')} CPUs, variant {r['scenes'][0]['variant'] if r['scenes'] else '-'}; "
             f"run finished {r.get('finished', '?')}: **{minutes} min {seconds} s** wall (goal <= 60 min), "
             f"{r['sub_images']:,} labelled sub-images.",
             "", "| scene | seconds | censored blocks (never converged) |", "|---|---|---|"]
    lines += [f"| {x['scene']} | {x['seconds']:.0f} | {x['censored']} |" for x in r["scenes"]]
    if resumed or done or r.get("failed"):
        lines += ["", f"Resumed scenes: {', '.join(resumed) or 'none'}; already built: "
                  f"{', '.join(done) or 'none'}; failed: {', '.join(r.get('failed') or {}) or 'none'}."]
    return "\n".join(lines)
