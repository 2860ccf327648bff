"""`noisestop evaluate`: DESIGN's metrics on held-out scenes, overall and per scene."""
from __future__ import annotations

import argparse

from learning.names import DEFAULT_TAU
from renderer.criteria.registry import criterion_class
from renderer.criteria.registry import names as criterion_names
from renderer.settings import ROW

from ..console import UsageError, emit_json, log
from . import arguments as arg


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("evaluate", help="metrics on held-out scenes, overall and per scene")
    p.add_argument("--data", required=True)
    p.add_argument("--model", default=None, help="model bundle (default: the bundled model)")
    p.add_argument("--criterion", default="model", choices=criterion_names())
    p.add_argument("--offset", type=arg.offset, default=None, help=ROW["offset"].help_text())
    p.add_argument("--threshold", type=arg.threshold, default=None, help=ROW["threshold"].help_text())
    p.add_argument("--tau", type=arg.tau, default=DEFAULT_TAU, help=arg.TAU_HELP + "; labels come from the "
                   "observer at this tau")
    p.add_argument("--min-spp", type=arg.spp, default=None,
                   help="no decision below this many spp (default: from the first level)")
    p.add_argument("--tile", type=arg.tile, default=None, metavar="PX",
                   help="decide per tile of PX pixels and score against the tile truth, with the same "
                        "figures per block beside them (default: whole blocks); --criterion model then gates "
                        "flip's tile verdicts with the model's block verdict, simulated on the stacks")
    p.add_argument("--scenes", default=None,
                   help="comma-separated scenes to evaluate (default: those the model was not trained on)")
    p.add_argument("--plots", default="out/evaluate", help="directory for the plots")
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_evaluate)


def cmd_evaluate(args: argparse.Namespace) -> int:
    from learning.models.bundle import load_model
    from learning.evaluation.evaluate import evaluate_model
    from learning.inputs.table import load_table

    for key in ("offset", "threshold"):      # what the criterion declares it takes
        if getattr(args, key) is not None and key not in criterion_class(args.criterion).settings:
            log.warning("--%s is ignored with --criterion %s", key, args.criterion)
    if args.criterion != "model" or args.tile:      # the model per tile: gated, simulated as it renders
        from renderer.simulation.simulate import evaluate_criterion_cli
        result = evaluate_criterion_cli(args.data, args.criterion, arg.scene_list(args.scenes),
                                        min_spp=args.min_spp, threshold=args.threshold, tau=args.tau,
                                        tile=args.tile, model=args.model, offset=args.offset)
        result["threshold"] = result["criterion"].get("threshold")
    else:
        model = load_model(args.model)
        offset = model.offset_at(args.tau) if args.offset is None else args.offset
        table = load_table(args.data, tau=args.tau, **model.table_options())
        trained_on = set(model.manifest.get("training", {}).get("train_scenes", []))
        scenes = arg.scene_list(args.scenes) or [s for s in table.scenes() if s not in trained_on]
        if not scenes:
            raise UsageError(f"every scene of {args.data} was used to train this model; "
                             "name the scenes to evaluate with --scenes")
        leaked = sorted(set(scenes) & trained_on)
        if leaked:
            log.warning("evaluating on scenes the model was trained on: %s", ", ".join(leaked))
        missing = sorted(set(scenes) - set(table.scenes()))
        if missing:
            raise UsageError(f"scenes not in {args.data}: {missing}")
        test = table.subset(table.scene_mask(scenes))
        result = evaluate_model(model, test, offset=offset, min_spp=args.min_spp)
        result["model"], result["tau"] = model.name, args.tau
        from learning.evaluation.plots import plot_thresholds
        result["plots"] = [str(p) for p in plot_thresholds(model, test, args.plots, offset=offset,
                                                           min_spp=args.min_spp)]
    if args.json:
        emit_json(result)
    else:
        _print_metrics(result)
    return 0


def _print_metrics(result: dict) -> None:
    from learning.evaluation.metrics import METRIC_NAMES
    knob = (f"offset {result['offset']:g}" if result.get("offset") is not None else
            f"threshold {result['threshold']:g}" if result.get("threshold") is not None else "")
    print(", ".join(x for x in (f"tau {result['tau']:g}" if result.get("tau") else "", knob) if x))
    width = max(len(s) for s in ["overall", *result["per_scene"]])
    print(f"{'':<{width}}  " + "  ".join(f"{m:>19}" for m in METRIC_NAMES))
    rows = [("overall", result), *sorted(result["per_scene"].items())]
    for name, r in rows:
        print(f"{name:<{width}}  " + "  ".join(f"{r[m]:>19.4f}" for m in METRIC_NAMES))
    if "end" in result:              # the simulated render's last image, judged by the block observer
        end = result["end"]
        print(f"blocks above tau at the end: {end['above_tau']} of {end['blocks']} (" + ", ".join(
            f"{s} {e['above_tau']}, worst {e['worst']:.4f}" for s, e in sorted(end["per_scene"].items())) + ")")
    if "blocks" in result:
        b = result["blocks"]
        print(f"per tile: {b['spp_ratio_vs_block_oracle']:.2f}x the block oracle's samples "
              f"(the tile oracle {b['tile_oracle_vs_block_oracle']:.2f}x); blocks holding an early tile "
              f"{result['early_block_rate']:.3f}")
    for p in result.get("plots", []):
        print(f"plot: {p}")
