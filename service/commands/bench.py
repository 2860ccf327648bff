"""`noisestop bench`: the door to the benchmarks (benchmarks/ of a source checkout), which
measure the figures of BENCHMARKS.md.

The benchmarks (load generators, attack drivers, charts) are not part of the installed
package or the serving image, so the service never imports them: this command finds the
checkout the packages were installed from (an editable install, or `python -m service.cli`
in the checkout) and loads them from there by name; from a plain install it says, in one
line, that it needs a checkout.
"""
from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path
from types import ModuleType

from learning.names import QUICK_MODES, SVM_KINDS, TRANSFER_KINDS

from ..console import UsageError, emit_json, log
from . import arguments as arg


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="measure the figures of BENCHMARKS.md")
    p.add_argument("what", nargs="*", default=["features", "crop"],
                   help="sections: features, crop, flip, models, render, passes, native, cost, equaltime, realscenes, oracle, service, "
                        "capacity, stability, reliability, hardening, dataset, inputs, criteria, tradeoff, ablation, step, "
                        "knobs, observer, tau, tilestop, skip, budget "
                        "(default: features crop)")
    p.add_argument("--data", default=None, help="labelled dataset of training scenes")
    p.add_argument("--heldout", default=None,
                   help="labelled dataset of held-out scenes every figure is measured on (make "
                        "heldout); without it a quarter of --data is held out, with a warning")
    p.add_argument("--out", default="out/bench", help="directory for plots")
    p.add_argument("--arches", type=arg.names_from(TRANSFER_KINDS, "transfer baseline"), default=None,
                   help=f"models: comma-separated transfer baselines ({', '.join(TRANSFER_KINDS)}; "
                        "default: all five; '' for none)")
    p.add_argument("--kinds", type=arg.names_from(SVM_KINDS, "SVM kind"), default=None,
                   help=f"models: comma-separated SVM kinds ({', '.join(SVM_KINDS)}; default: all six)")
    p.add_argument("--input", "--quick", dest="quick", type=arg.quick_modes, default=("albedo",),
                   help="models: the quick images of the feature models, comma-separated "
                        f"({', '.join(QUICK_MODES)}; default albedo)")
    p.add_argument("--update", default=None, metavar="FILE",
                   help="rewrite the marked sections of FILE (e.g. BENCHMARKS.md) with the results")
    p.add_argument("--repeats", type=arg.int_in(1, 10_000), default=30)
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_bench)


#: the benchmarks' folder in a source checkout, beside the packages
BENCHMARKS = "benchmarks"


def checkout_root() -> Path | None:
    """The source checkout these packages live in (the folder holding `service/` and
    `benchmarks/`), or None for a plain install (site-packages has no benchmarks)."""
    root = Path(__file__).resolve().parents[2]
    return root if (root / BENCHMARKS / "bench.py").is_file() and (root / "pyproject.toml").is_file() else None


def load_benchmarks() -> ModuleType:
    """`benchmarks.bench` of the checkout, or UsageError (one line, exit 2) without one."""
    root = checkout_root()
    if root is None:
        raise UsageError("the benchmarks run from a source checkout (benchmarks/ beside the packages, "
                         "then `make bench`); this install has none")
    if str(root) not in sys.path:
        sys.path.insert(0, str(root))
    return importlib.import_module(f"{BENCHMARKS}.bench")


def cmd_bench(args: argparse.Namespace) -> int:
    bench = load_benchmarks()
    unknown = sorted(set(args.what) - set(bench.SECTIONS))
    if unknown:
        raise UsageError(f"unknown bench sections {unknown}; known: {', '.join(bench.SECTIONS)}")
    if args.update:        # before measuring: a FILE that cannot be rewritten costs no run
        try:
            bench.check_target(Path(args.update))
        except (ValueError, OSError) as exc:
            raise UsageError(f"--update {exc}") from None

    def update(name: str, markdown: str) -> None:   # section by section: ctrl-c loses nothing done
        bench.update_markdown(Path(args.update), {name: markdown})
        log.info("updated %s: section %s", args.update, name)
    results = bench.run_all(repeats=args.repeats, only=tuple(args.what), data=args.data,
                            out_dir=args.out, arches=args.arches, kinds=args.kinds, quick=args.quick,
                            on_section=update if args.update else None, heldout=args.heldout)
    if args.json:
        emit_json(results)
    else:
        print(bench.format_results(results))
    for name, why in results["failed"].items():
        log.error("bench %s not measured: %s", name, why)
    return 1 if results["failed"] else 0
