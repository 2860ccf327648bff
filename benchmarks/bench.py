"""`noisestop bench`: runs the sections of BENCHMARKS.md and rewrites their marked parts.

Every figure is a median over repeats after a warm-up call; the accuracy cost of each
speed choice is reported beside it. The sections live in bench_features, bench_flip,
bench_models, bench_passes (renders and passes), bench_native and bench_cost (against
`mi.render` and the uniform loop), bench_criteria, bench_tradeoff and bench_step (the
stopping decisions), bench_service, stability and reliability; marked_sections rewrites
the marked parts.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .bench_criteria import bench_criteria, md_criteria
from .bench_equal_time import kind_of
from .bench_features import bench_crop, bench_features, md_crop, md_features
from .bench_flip import bench_flip, md_flip
from .bench_models import (bench_ablation, bench_dataset, bench_inputs, bench_knobs, bench_models, md_ablation,
                           md_cost_accuracy, md_dataset, md_inputs, md_knobs, md_models, saved_comparisons)
from .bench_budget import bench_budget, md_budget
from .bench_observer import bench_observer, bench_tau, md_observer, md_tau
from .bench_tile_stop import bench_tile_stop, md_tile_stop
from .bench_skip import bench_skip, md_skip
from .bench_passes import bench_render, md_render
from .bench_step import bench_step, md_step
from .bench_tradeoff import bench_tradeoff, md_tradeoff
from .marked_sections import check_target, update_markdown  # noqa: F401 - the door (service/commands/bench.py) checks and writes with them


log = logging.getLogger(__name__)


# sections that need only the datasets: name -> (measure(data, heldout), markdown(result))
DATASET_SECTIONS = {"dataset": (bench_dataset, md_dataset), "inputs": (bench_inputs, md_inputs),
                    "criteria": (bench_criteria, md_criteria),
                    "tradeoff": (bench_tradeoff, md_tradeoff), "ablation": (bench_ablation, md_ablation),
                    "step": (bench_step, md_step), "knobs": (bench_knobs, md_knobs),
                    "observer": (bench_observer, md_observer), "tau": (bench_tau, md_tau),
                    "tilestop": (bench_tile_stop, md_tile_stop), "skip": (bench_skip, md_skip),
                    "budget": (bench_budget, md_budget)}


#: dataset sections measured on the held-out stacks alone (no training data read)
HELDOUT_ONLY = {"tilestop", "skip"}

SECTIONS = ("features", "crop", "flip", "models", "render", "passes", "native", "cost", "equaltime", "realscenes", "oracle", "service",
            "capacity", "stability",
            "reliability", "hardening", *DATASET_SECTIONS)


def run_all(repeats: int = 30, only: tuple[str, ...] = ("features", "crop"), data: str | None = None,
            out_dir: str = "out/bench", arches: tuple[str, ...] | None = None,
            kinds: tuple[str, ...] | None = None, quick: tuple[str, ...] = ("albedo",),
            on_section: Callable[[str, str], None] | None = None,
            heldout: str | None = None) -> dict[str, Any]:
    """Measure the sections in `only`; `quick`: the quick images the models section compares
    (feature models are trained once per mode). `on_section(name, markdown)` is called as
    each section finishes, so an interrupted run keeps what it measured; a section that
    cannot run (e.g. no dataset build on record) is reported in results["failed"] and the
    others still run."""
    from learning.training.train import SVM_KINDS
    from learning.data.variant import select_variant
    variant = select_variant()
    results: dict[str, Any] = {"variant": variant, "seconds": {}, "failed": {}}
    markdown: dict[str, str] = {}
    needs_data = ({"models", *DATASET_SECTIONS} - HELDOUT_ONLY) & set(only)
    if needs_data and not data:
        raise ValueError(f"bench {', '.join(sorted(needs_data))} needs --data DIR (a labelled dataset)")

    def measure(name: str, run: Callable[[], Any], md: Callable[[Any], str]) -> None:
        t0 = time.perf_counter()
        try:
            results[name] = run()
        except (ValueError, FileNotFoundError) as exc:   # one section's problem spares the others
            log.error("bench %s: %s", name, exc)
            results["failed"][name] = str(exc)
            return
        markdown[name] = md(results[name])
        results["seconds"][name] = time.perf_counter() - t0
        log.info("bench %s: %.0f s", name, results["seconds"][name])
        if on_section is not None:
            on_section(name, markdown[name])

    if "features" in only:
        measure("features", lambda: bench_features(repeats), lambda r: md_features(r, variant))
    if "crop" in only:
        measure("crop", lambda: bench_crop(repeats=max(1, min(repeats, 3))), md_crop)
    if "flip" in only:
        measure("flip", lambda: bench_flip(repeats, datasets=tuple(d for d in (data, heldout) if d)), md_flip)
    if "models" in only:
        plain_done = False
        for q in quick:
            # raw-pixel and transfer models read the block whatever the quick image (measured
            # with the first such mode), and the noise image with halves (measured there)
            full = q == "halves" or not plain_done
            plain_done = plain_done or q != "halves"
            k, a = (kinds, arches) if full else (tuple(x for x in (kinds or SVM_KINDS) if x.startswith("dsvm")), ())
            measure("models" if q == "albedo" else "models_halves" if q == "halves" else f"models_quick_{q}",
                    lambda k=k, a=a, q=q: bench_models(data, Path(out_dir), a, k, q, heldout=heldout), md_models)
        measure("cost_accuracy", lambda: saved_comparisons(data, Path(out_dir), heldout), md_cost_accuracy)
    if "render" in only:
        measure("render", bench_render, md_render)
    if "passes" in only:
        from .bench_passes import bench_passes, md_passes
        measure("passes", bench_passes, md_passes)
    if "native" in only:
        from .bench_native import bench_native, md_native
        # the figures are the device's: a GPU run fills a section of its own
        measure("native_gpu" if variant.startswith("cuda") else "native", bench_native, md_native)
    if "cost" in only:
        from .bench_cost import bench_cost, md_cost
        # the cost per kept sample, in parts; a GPU run fills a section of its own
        measure("cost_gpu" if variant.startswith("cuda") else "cost", bench_cost, md_cost)
    if "equaltime" in only:
        from .bench_equal_time import SECTION, bench_equal_time, md_equal_time
        # the default render against mi.render at equal wall time, per device
        measure(SECTION[kind_of(variant)], bench_equal_time, md_equal_time)
    if "realscenes" in only:
        from .bench_realscenes import SECTION as REAL, bench_realscenes, md_realscenes
        # the default render against mi.render on the public real-scene suite, per device
        measure(REAL[kind_of(variant)], bench_realscenes, md_realscenes)
    if "oracle" in only:
        from .bench_passes import bench_oracle, md_oracle
        measure("oracle", lambda: bench_oracle(max(1, min(repeats, 3))), md_oracle)
    for name, (run, md) in DATASET_SECTIONS.items():
        if name in only:
            measure(name, lambda run=run, name=name: run(data, heldout, out_dir=out_dir) if name == "tradeoff"
                    else run(data, heldout), md)
    if "stability" in only:
        measure("stability", stability_section, md_stability)
    if "service" in only:
        from .bench_service import bench_service, md_service
        measure("service", bench_service, md_service)
    if "capacity" in only:
        from .bench_capacity import bench_capacity, md_capacity
        measure("capacity", bench_capacity, md_capacity)
    if "reliability" in only:
        from .hardening import md_hardening
        from .reliability import bench_reliability, md_reliability
        measure("reliability", bench_reliability, md_reliability)
        if "reliability" in results:                     # its hardening part: a section of its own
            markdown["hardening"] = md_hardening(results["reliability"]["hardening"])
            if on_section is not None:
                on_section("hardening", markdown["hardening"])
    if "hardening" in only and "reliability" not in only:     # reliability includes it
        from .hardening import bench_hardening, md_hardening
        measure("hardening", bench_hardening, md_hardening)
    results["markdown"] = markdown
    return results


def stability_section() -> dict[str, Any]:
    import tempfile

    from . import stability
    with tempfile.TemporaryDirectory() as tmp:
        return {"blocks": stability.matrix(), "other": stability.other_cells(tmp)}


def md_stability(r: dict[str, Any]) -> str:
    from . import stability
    return (stability.markdown(r["blocks"]) + "\n\n| other extreme | behaviour |\n|---|---|\n"
            + "\n".join(f"| {k} | {v} |" for k, v in r["other"].items()))


def format_results(r: dict[str, Any]) -> str:
    return "\n\n".join(f"## {name}\n{body}" for name, body in r["markdown"].items())
