"""Sub-command definitions: each adds its arguments and a handler that calls the packages."""
from __future__ import annotations

import argparse
import math
import os
import re
import time
from collections.abc import Callable

# the choices and documented ranges (issue 14) come from their one home, in modules that
# import nothing heavy; frame and block sizes are also checked against noisefeat.bounds
# (environment-configurable) by the commands themselves
from learning.names import DEFAULT_INPUT, MODEL_KINDS, OFFSET_LIMIT, QUICK_MODES, TRANSFER_INPUTS, TRANSFER_KINDS
from noisefeat.bounds import EXPOSURE_RANGE, MIN_SIDE
from renderer.names import CRITERIA, DEFAULT_CRITERION
from renderer.settings import MAX_SPP

from .console import UsageError, emit_json, log

MAX_SIDE = 65536
MAX_SEED = 2**32 - 1


def _int_in(low: int, high: int | None = None) -> Callable[[str], int]:
    """argparse type: a whole number in [low, high] (high None: no upper bound)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text[:40]!r}") from None
        if value < low or (high is not None and value > high):
            shown = value if len(str(value)) < 30 else f"a {len(str(value))}-digit number"
            bound = f" and <= {high}" if high is not None else ""
            raise argparse.ArgumentTypeError(f"expected a number >= {low}{bound}, got {shown}")
        return value
    parse.__name__ = "whole number"
    return parse


def _float_in(low: float, high: float, *, open_low: bool = False) -> Callable[[str], float]:
    """argparse type: a finite number in [low, high] ((low, high] with open_low)."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text[:40]!r}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"expected a finite number, got {text[:40]!r}")
        if value < low or value > high or (open_low and value == low):
            raise argparse.ArgumentTypeError(
                f"expected a number in {'(' if open_low else '['}{low:g}, {high:g}], got {value:g}")
        return value
    parse.__name__ = "number"
    return parse


_positive_int = _int_in(1)
_spp = _int_in(1, MAX_SPP)
_side = _int_in(1, MAX_SIDE)
_seed = _int_in(0, MAX_SEED)
_offset = _float_in(-OFFSET_LIMIT, OFFSET_LIMIT)
_exposure = _float_in(*EXPOSURE_RANGE)
_fraction = _float_in(0.0, 1.0, open_low=True)
_rate = _float_in(0.0, 1.0)
_seconds = _float_in(0.0, 3600.0, open_low=True)
_threshold = _float_in(0.0, 1000.0)


def _check_frame(height: int, width: int, grid: tuple[int, int], what: str) -> None:
    """The frame and block bounds of noisefeat.bounds (environment-configurable), as a usage error."""
    from noisefeat.bounds import SizeBounds
    try:
        SizeBounds.from_env().check_frame(height, width, grid)
    except ValueError as exc:
        raise UsageError(f"{what}: {exc}") from None


_DEFINE_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def _resolution(text: str) -> int | tuple[int, int]:
    """`--resolution N|WxH`, each side within the frame bounds' range."""
    from renderer.scenes import parse_resolution

    try:
        value = parse_resolution(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    for side in value if isinstance(value, tuple) else (value,):
        if side > MAX_SIDE:
            raise argparse.ArgumentTypeError(f"a side of {side} px is over the largest, {MAX_SIDE}")
    return value


def _define(text: str) -> tuple[str, str]:
    """`-D key=value`: key a name as in an XML scene's <default name=...>, value non-empty."""
    key, sep, value = text.partition("=")
    if not sep or not _DEFINE_KEY.fullmatch(key.strip()) or not value.strip():
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE with KEY a parameter name, got {text!r}")
    return key.strip(), value.strip()


def _quick_modes(text: str) -> tuple[str, ...]:
    modes = tuple(m.strip() for m in text.split(",") if m.strip())
    bad = [m for m in modes if m not in QUICK_MODES]
    if not modes or bad or len(set(modes)) != len(modes):
        raise argparse.ArgumentTypeError(
            f"expected distinct quick images from {', '.join(QUICK_MODES)}, comma-separated; got {text!r}")
    return modes


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("scenes", help="list the built-in scenes")
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_scenes)

    _register_dataset(sub)

    p = sub.add_parser("features", help="render a scene at low spp and print each block's 26 features")
    p.add_argument("--scene", default=None, help="built-in scene name or Mitsuba 3 XML file")
    p.add_argument("--resolution", type=_side, default=128)
    p.add_argument("--spp", type=_spp, default=16)
    p.add_argument("--grid", type=_side, nargs=2, default=(4, 4), metavar=("ROWS", "COLS"))
    p.add_argument("--exposure", type=_exposure, default=0.0)
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_features)

    _register_learning(sub)
    _register_render(sub)
    _register_serve(sub)

    p = sub.add_parser("bench", help="measure the figures of BENCHMARKS.md")
    p.add_argument("what", nargs="*", default=["features", "crop"],
                   help="sections: features, crop, flip, models, render, passes, service, stability, reliability, "
                        "dataset, inputs, criteria, tradeoff, ablation, step, knobs (default: features crop)")
    p.add_argument("--data", default=None, help="labelled dataset of training scenes")
    p.add_argument("--heldout", default=None,
                   help="labelled dataset of held-out scenes every figure is measured on (make "
                        "heldout); without it a quarter of --data is held out, with a warning")
    p.add_argument("--out", default="out/bench", help="directory for plots")
    p.add_argument("--arches", default=None,
                   help="models: comma-separated transfer baselines (default: all five; '' for none)")
    p.add_argument("--kinds", default=None, help="models: comma-separated SVM kinds (default: all six)")
    p.add_argument("--input", "--quick", dest="quick", type=_quick_modes, default=("albedo",),
                   help="models: the quick images of the feature models, comma-separated "
                        f"({', '.join(QUICK_MODES)}; default albedo)")
    p.add_argument("--update", default=None, metavar="FILE",
                   help="rewrite the marked sections of FILE (e.g. BENCHMARKS.md) with the results")
    p.add_argument("--repeats", type=_int_in(1, 10_000), default=30)
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_bench)


def _add_pool_arguments(p: argparse.ArgumentParser, purpose: str) -> None:
    """--workers N | --scheduler ADDRESS: where per-scene tasks run (renderer.farm)."""
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=_int_in(1, 1024), default=None,
                       help=f"local process workers{purpose} (default: one per core)")
    where.add_argument("--scheduler", default=None,
                       help=f"Dask scheduler address{purpose}, e.g. tcp://host:8786")


def _register_dataset(sub: argparse._SubParsersAction) -> None:
    ds = sub.add_parser("dataset", help="build, import and check labelled datasets")
    dsub = ds.add_subparsers(dest="dataset_command", metavar="ACTION", required=True)

    p = dsub.add_parser("build", help="render and label stacks (format v1) for scenes")
    p.add_argument("--out", required=True, help="dataset directory (one sub-directory per scene)")
    p.add_argument("--scenes", default=None,
                   help="comma-separated built-in names, XML files, procedural scenes (proc-0042, or "
                        "procedural:N for the first N, procedural:A-B for seeds A..B-1), or the sets "
                        "'training' (the training library, the default) and 'heldout' (scenes kept out "
                        "of all training)")
    p.add_argument("--resolution", type=_side, default=512)
    p.add_argument("--block", type=_int_in(MIN_SIDE, MAX_SIDE), default=None,
                   help="block side in pixels (default: a 4x4 grid, the paper's); must divide --resolution")
    p.add_argument("--step", type=_spp, default=101, help="spp added per level")
    p.add_argument("--levels", type=_int_in(1, 100_000), default=100)
    p.add_argument("--reference-spp", type=_spp, default=None,
                   help="default: 4 x the last level")
    p.add_argument("--seed", type=_seed, default=0)
    p.add_argument("--tau", type=_fraction, default=0.02, help="virtual observer threshold on FLIP")
    p.add_argument("--no-contact-sheets", action="store_true")
    _add_pool_arguments(p, "")
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_dataset_build)

    p = dsub.add_parser("import-lisic", help="import a dataset in the LISIC layout")
    p.add_argument("src")
    p.add_argument("--out", required=True)
    p.add_argument("--every", type=_int_in(1, 1_000_000), default=1, help="keep one image in EVERY")
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_import_lisic)

    p = dsub.add_parser("check", help="validate a dataset and report every problem found")
    p.add_argument("dir")
    p.add_argument("--quick", action="store_true", help="skip reading the images")
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_dataset_check)


def cmd_dataset_build(args: argparse.Namespace) -> int:
    from renderer.dataset import build_dataset
    from renderer.procedural import expand_procedural
    from renderer.scenes import list_scenes
    from renderer.stackbuild import BuildSettings

    sets = {"training": False, "heldout": True}   # named sets of built-in scenes
    scenes = []
    for s in (args.scenes or "training").split(","):
        s = s.strip()
        family = expand_procedural(s)
        scenes += family if family is not None else [name for name, _ in list_scenes(sets[s])] \
            if s in sets else [s] if s else []
    if args.step * args.levels > MAX_SPP:
        raise UsageError(f"--step {args.step} x --levels {args.levels} is {args.step * args.levels} spp, "
                         f"more than {MAX_SPP}")
    ref = args.reference_spp or min(4 * args.step * args.levels, MAX_SPP)
    if ref < args.step * args.levels:
        raise UsageError(f"--reference-spp {ref} is below the last level's {args.step * args.levels} spp")
    grid = (4, 4)
    if args.block is not None:
        if args.resolution % args.block:
            raise UsageError(f"--block {args.block} does not divide --resolution {args.resolution}: "
                             "stacks keep a grid of equal blocks")
        grid = (args.resolution // args.block,) * 2
    _check_frame(args.resolution, args.resolution, grid, "--resolution/--block")
    settings = BuildSettings(resolution=args.resolution, step=args.step, levels=args.levels, grid=grid,
                             reference_spp=ref, seed=args.seed, tau=args.tau,
                             contact_sheet=not args.no_contact_sheets)
    summary = build_dataset(scenes, args.out, settings, workers=args.workers, scheduler=args.scheduler)
    if args.json:
        emit_json(summary)
    else:
        for r in summary["scenes"]:
            th = ", ".join("-" if t is None else str(t) for t in r["thresholds"])
            print(f"{r['scene']:<14} {r['seconds']:7.1f} s  thresholds: {th}")
        print(f"{len(summary['scenes'])} scenes, {summary['sub_images']} labelled sub-images, "
              f"{summary['wall_s']:.0f} s wall, in {summary['out']}")
    for scene, err in summary["failed"].items():
        log.error("scene %s failed: %s", scene, err)
    return 1 if summary["failed"] else 0


def cmd_import_lisic(args: argparse.Namespace) -> int:
    from learning.data.lisic import import_lisic
    dirs = import_lisic(args.src, args.out, every=args.every)
    if args.json:
        emit_json({"stacks": [str(d) for d in dirs]})
    else:
        for d in dirs:
            print(d)
    return 0


def cmd_dataset_check(args: argparse.Namespace) -> int:
    from learning.data.check import ERROR, check_dataset
    problems = check_dataset(args.dir, deep=not args.quick)
    errors = [p for p in problems if p.severity == ERROR]
    if args.json:
        emit_json({"ok": not errors, "problems": [
            {"path": str(p.path), "message": p.message, "severity": p.severity} for p in problems]})
    else:
        for p in problems:
            print(p)
        print(f"{args.dir}: {len(errors)} error(s), {len(problems) - len(errors)} warning(s)")
    return 1 if errors else 0


def _register_learning(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train a model on a dataset (scenes held out for evaluation)")
    p.add_argument("--data", required=True, help="dataset directory")
    p.add_argument("--model", default="dsvm_as", choices=MODEL_KINDS,
                   help="model kind (default dsvm_as); vgg19 ... densenet201: a transfer baseline "
                        "(frozen conv base + the paper's head, README \"Transfer baselines\")")
    p.add_argument("--weights", default=None, metavar="FILE",
                   help="transfer baselines: a local ImageNet state_dict for the base (never downloaded; "
                        "default: the torch hub cache, else an untrained base, labelled so)")
    p.add_argument("--out", required=True, help="model bundle directory to write")
    p.add_argument("--test-scenes", default=None,
                   help="comma-separated scenes of --data held out of training ('' for none; default: "
                        "every 4th by name, none with --heldout)")
    p.add_argument("--heldout", default=None, metavar="DIR",
                   help="labelled dataset of held-out scenes to report on (then every scene of --data "
                        "is trained on, unless --test-scenes says otherwise)")
    p.add_argument("--initial-scene", default=None, help="active kinds: the initially labelled scene(s), comma-separated (default: the "
                        "scenes closest to half converged, at least 500 sub-images)")
    p.add_argument("--label-budget", type=_fraction, default=0.25,
                   help="active kinds: largest fraction of the pool's labels to query")
    p.add_argument("--no-cv", action="store_true", help="skip the C/gamma cross-validation")
    p.add_argument("--max-early-stop", type=_rate, default=0.05,
                   help="calibrate the decision offset on leave-one-scene-out scores of the "
                        "training scenes to keep early stops at or below this rate (default 0.05)")
    p.add_argument("--no-calibrate", action="store_true", help="keep the decision offset at 0")
    p.add_argument("--input", "--quick", dest="quick", choices=QUICK_MODES, default=DEFAULT_INPUT,
                   help="feature models' input: halves (noise features of the half buffers next to "
                        "features of the block, README \"Model inputs\"), or the paper's quick image "
                        "subtracted from the features: the albedo AOV, direct lighting, or none (a "
                        f"flat image: features of the current block alone); default {DEFAULT_INPUT}. "
                        "Transfer baselines: halves (the displayed noise picture of the half buffers) "
                        "or none (the block itself, the paper's)")
    p.add_argument("--composition", default=None,
                   help="input halves: which parts of the half-buffer input a feature model reads, "
                        "joined by '+' (n noise, c current, r ratios, l luminance, f FLIP; README "
                        "\"Model inputs\"; default: the measured best, learning.inputs.noise_input.HALVES)")
    p.add_argument("--seed", type=_seed, default=0)
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_train)

    p = sub.add_parser("calibrate", help="calibrate the flip criterion's c on training scenes")
    p.add_argument("--data", required=True, help="labelled dataset of training scenes (never held-out ones)")
    p.add_argument("--criterion", choices=("flip",), default="flip")
    p.add_argument("--max-early-stop", type=_rate, default=0.05,
                   help="largest early-stop rate accepted on the training scenes (default 0.05)")
    p.add_argument("--min-spp", type=_spp, default=None,
                   help="no decision below this many spp (default: from the first level)")
    p.add_argument("--out", default=None,
                   help="calibration file to write (default: the package's learning/flip.json)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_calibrate)

    p = sub.add_parser("pretrain", help="pre-train the feature base's conv layers as a denoiser")
    p.add_argument("--data", required=True, help="dataset directory (training scenes only are used)")
    p.add_argument("--out", default=None,
                   help="safetensors file to write (default: the package's pretrained.safetensors)")
    p.add_argument("--test-scenes", default=None, help="scenes to keep out (default: every 4th by name)")
    p.add_argument("--steps", type=_int_in(1, 1_000_000), default=400)
    p.add_argument("--lr", type=_float_in(0.0, 10.0, open_low=True), default=0.003)
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_pretrain)

    p = sub.add_parser("evaluate", help="metrics on held-out scenes, overall and per scene")
    p.add_argument("--data", required=True)
    p.add_argument("--model", default=None, help="model bundle (default: the bundled model)")
    p.add_argument("--criterion", default="model", choices=CRITERIA)
    p.add_argument("--offset", type=_offset, default=None,
                   help="--criterion model: decision offset, the speed/accuracy knob (default: the "
                        "model's calibrated offset; larger stops later)")
    p.add_argument("--threshold", type=_threshold, default=None,
                   help="--criterion flip: c (default: the shipped calibration); --criterion "
                        "variance: the noise threshold (default 0.01)")
    p.add_argument("--min-spp", type=_spp, default=None,
                   help="no decision below this many spp (default: from the first level)")
    p.add_argument("--scenes", default=None,
                   help="comma-separated scenes to evaluate (default: those the model was not trained on)")
    p.add_argument("--plots", default="out/evaluate", help="directory for the plots")
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_evaluate)


def _scene_list(text: str | None) -> list[str] | None:
    return [s.strip() for s in text.split(",") if s.strip()] if text else None


def _composition(args: argparse.Namespace, raw: bool) -> dict[str, str]:
    """{'composition': C} for a feature model on the half buffers, else {}."""
    if raw or args.quick != "halves":
        if args.composition is not None:
            raise UsageError("--composition applies to feature models with --input halves only")
        return {}
    from learning.inputs.noise_input import HALVES, parts_of
    composition = args.composition or HALVES
    try:
        parts_of(composition)
    except ValueError as exc:
        raise UsageError(f"--composition: {exc}") from None
    return {"composition": composition}


def cmd_train(args: argparse.Namespace) -> int:
    from learning.models.bundle import Model, save_model
    from learning.evaluation.evaluate import evaluate_model
    from learning.inputs.table import load_table
    from learning.training.train import train_model

    if not 0 < args.label_budget <= 1:
        raise UsageError(f"--label-budget must be in (0, 1], got {args.label_budget}")
    transfer = args.model in TRANSFER_KINDS
    if transfer and (args.quick not in TRANSFER_INPUTS or args.composition is not None):
        raise UsageError(f"--model {args.model} reads pictures: --input {' or '.join(TRANSFER_INPUTS)}, "
                         f"no {'--composition' if args.quick in TRANSFER_INPUTS else '--input ' + args.quick}")
    if args.weights is not None and not transfer:
        raise UsageError("--weights applies to the transfer baselines only "
                         f"({', '.join(TRANSFER_KINDS)})")
    if args.weights is not None and not os.path.isfile(args.weights):
        raise UsageError(f"--weights {args.weights}: no such file (ImageNet weights are never downloaded)")
    raw = args.model.startswith("svm")
    opts = {"image": True, "quick": args.quick} if transfer else \
        {"raw": raw, "quick": args.quick, **_composition(args, raw)}
    table = load_table(args.data, **opts)
    if not 0 <= args.max_early_stop <= 1:
        raise UsageError(f"--max-early-stop must be in [0, 1], got {args.max_early_stop}")
    test_scenes = [] if args.test_scenes == "" else _scene_list(args.test_scenes)   # '': none
    if args.heldout and test_scenes is None:
        test_scenes = []
    _refuse_heldout([s for s in table.scenes() if s not in (test_scenes or [])], "train")
    max_early_stop = None if args.no_calibrate else args.max_early_stop
    if transfer:
        from learning.models.transfer_bundle import TransferModel, save_transfer_model
        from learning.training.train_transfer import train_transfer
        try:
            est, summary = train_transfer(args.model, args.data, quick=args.quick, weights=args.weights,
                                          test_scenes=test_scenes, table=table, seed=args.seed,
                                          max_early_stop=max_early_stop)
        except (FileNotFoundError, ImportError) as exc:      # --weights missing, torchvision broken
            raise UsageError(str(exc)) from None
    else:
        est, summary = train_model(args.model, args.data, test_scenes=test_scenes,
                                   initial_scene=args.initial_scene, cv=not args.no_cv, seed=args.seed,
                                   max_label_fraction=args.label_budget, table=table,
                                   max_early_stop=max_early_stop, quick=args.quick)
    if args.heldout:
        from learning.evaluation.generalisation import check_disjoint
        test = load_table(args.heldout, **opts)
        check_disjoint(summary["train_scenes"], test.scenes())
        summary["heldout"] = {"data": str(args.heldout), "scenes": test.scenes()}
    else:
        test = table.subset(table.scene_mask(summary["test_scenes"]))
    extra = {"quick": args.quick} if transfer or not raw or args.quick == "halves" else {}
    extra.update({} if transfer else _composition(args, raw))
    model = (TransferModel if transfer else Model)(est, {"kind": args.model, "input": summary["input"], **extra})
    metrics = evaluate_model(model, test) if len(test) else {}
    metrics = {k: v for k, v in metrics.items() if k != "per_scene"}
    if transfer:
        save_transfer_model(est, args.out, quick=args.quick, training=summary, metrics=metrics)
    else:
        save_model(est, args.out, kind=args.model, input=summary["input"], training=summary,
                   metrics=metrics, extra=extra)
    result = {"model": args.out, "kind": args.model, "train_s": summary["train_s"],
              **({"base": summary["base"], "input": args.quick} if transfer else {}),
              "offset": summary["offset"],
              "labels": summary.get("n_labels"), "label_fraction": summary.get("label_fraction"),
              "test_scenes": test.scenes(), **{k: metrics.get(k) for k in
                                                         ("precision", "f1", "early_stop_rate")}}
    if args.json:
        emit_json(result)
    else:
        print(f"{summary.get('base', args.model)} -> {args.out}: trained in {summary['train_s']:.1f} s on "
              f"{len(summary['train_scenes'])} scenes, {summary.get('n_labels')} labels "
              f"({100 * summary.get('label_fraction', 1):.0f}% of the training sub-images)")
        if "calibration" in summary:
            c = summary["calibration"]["chosen"]
            print(f"decision offset {summary['offset']:.2f}: leave-one-scene-out early stops "
                  f"{c['early_stop_rate']:.3f}, samples {c['spp_ratio_vs_oracle']:.2f} x oracle")
        if metrics:
            print(f"held-out {', '.join(test.scenes())}: precision {metrics['precision']:.3f}, "
                  f"f1 {metrics['f1']:.3f}, early stops {metrics['early_stop_rate']:.3f}, "
                  f"samples {metrics['spp_ratio_vs_oracle']:.2f} x oracle")
    return 0


def _refuse_heldout(scenes: list[str], what: str) -> None:
    """The built-in held-out scenes take no part in training or calibration."""
    from learning.evaluation.generalisation import check_disjoint
    from renderer.scenes import list_scenes
    try:
        check_disjoint(scenes, [n for n, _ in list_scenes(heldout=True)])
    except ValueError as exc:
        raise UsageError(f"{what}: {exc} (renderer/heldout.py)") from None


def cmd_calibrate(args: argparse.Namespace) -> int:
    import datetime
    import json
    from pathlib import Path

    from learning.evaluation.calibrate import calibrate_flip
    from learning.inputs.halves import FLIP_CALIBRATION
    from learning.data.stack import dataset_fingerprint, list_stacks, read_stack

    if not 0 <= args.max_early_stop <= 1:
        raise UsageError(f"--max-early-stop must be in [0, 1], got {args.max_early_stop}")
    stacks = [read_stack(p) for p in list_stacks(args.data)]
    if not stacks:
        raise UsageError(f"{args.data}: no stacks found")
    _refuse_heldout([s.scene for s in stacks], "calibrate")
    cal = calibrate_flip(stacks, args.max_early_stop, min_spp=args.min_spp)
    cal.update(criterion="flip", data=str(args.data), fingerprint=dataset_fingerprint(args.data),
               observer={"ppd": 67, "display": "clip+srgb"},
               calibrated=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"))
    out = Path(args.out) if args.out else FLIP_CALIBRATION
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(json.dumps(cal, indent=1, default=float) + "\n")
    tmp.replace(out)
    chosen = cal["chosen"]
    if args.json:
        emit_json({"c": cal["c"], "out": str(out), **{k: chosen[k] for k in ("early_stop_rate",
                                                                          "spp_ratio_vs_oracle")}})
    else:
        print(f"flip: c = {cal['c']:g} on {len(stacks)} training scenes: early stops "
              f"{chosen['early_stop_rate']:.3f} (target {args.max_early_stop:g}), samples "
              f"{chosen['spp_ratio_vs_oracle']:.3f} x oracle; wrote {out}")
    return 0


def cmd_pretrain(args: argparse.Namespace) -> int:
    from learning.models.pretrain import pretrain_base
    from learning.data.stack import list_stacks, read_stack
    from learning.evaluation.generalisation import default_test_scenes
    from noisefeat.weights import PRETRAINED_FILE, save_kernels

    stacks = [read_stack(p) for p in list_stacks(args.data)]
    held = set(_scene_list(args.test_scenes) or default_test_scenes([s.scene for s in stacks]))
    train = [s for s in stacks if s.scene not in held]
    base, report = pretrain_base(train, steps=args.steps, lr=args.lr)
    out = args.out or PRETRAINED_FILE
    save_kernels(out, base.kernels(), {"init": "denoiser pre-training", "scenes": ",".join(report["scenes"]),
                                       "steps": str(args.steps), "lr": str(args.lr)})
    report["out"], report["hash"] = str(out), base.hash
    if args.json:
        emit_json(report)
    else:
        print(f"conv base pre-trained on {len(train)} scenes ({report['pairs']} block pairs) in "
              f"{report['seconds']:.0f} s: MSE(O_12, reference) {report['mse_smoothing_init']:.2f} "
              f"-> {report['mse_trained']:.2f} (noisy input: {report['mse_noisy']:.2f}); wrote {out}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from learning.models.bundle import load_model
    from learning.evaluation.evaluate import evaluate_model
    from learning.inputs.table import load_table

    if args.criterion != "model" and args.offset is not None:
        log.warning("--offset is ignored with --criterion %s (it moves the model's decision)", args.criterion)
    if args.criterion not in ("flip", "variance") and args.threshold is not None:
        log.warning("--threshold is ignored with --criterion %s", args.criterion)
    if args.criterion != "model":
        from renderer.simulate import evaluate_criterion_cli
        result = evaluate_criterion_cli(args.data, args.criterion, _scene_list(args.scenes),
                                        min_spp=args.min_spp, threshold=args.threshold)
        result["threshold"] = result["criterion"].get("threshold")
    else:
        model = load_model(args.model)
        table = load_table(args.data, **model.table_options())
        trained_on = set(model.manifest.get("training", {}).get("train_scenes", []))
        scenes = _scene_list(args.scenes) or [s for s in table.scenes() if s not in trained_on]
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
        result = evaluate_model(model, test, offset=args.offset, min_spp=args.min_spp)
        result["model"] = model.name
        from learning.evaluation.plots import plot_thresholds
        result["plots"] = [str(p) for p in plot_thresholds(model, test, args.plots, offset=args.offset,
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
    if knob:
        print(knob)
    width = max(len(s) for s in ["overall", *result["per_scene"]])
    print(f"{'':<{width}}  " + "  ".join(f"{m:>19}" for m in METRIC_NAMES))
    rows = [("overall", result), *sorted(result["per_scene"].items())]
    for name, r in rows:
        print(f"{name:<{width}}  " + "  ".join(f"{r[m]:>19.4f}" for m in METRIC_NAMES))
    for p in result.get("plots", []):
        print(f"plot: {p}")


def _register_render(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("render", help="adaptive progressive render: stop sampling blocks that look converged")
    p.add_argument("--scene", default=None,
                   help="built-in scene name or Mitsuba 3 XML file; several comma-separated (default: cornell)")
    p.add_argument("--out", required=True, help="output directory (several scenes: one sub-directory each)")
    source = p.add_mutually_exclusive_group()
    source.add_argument("--model", default=None, help="model bundle directory (default: the bundled model)")
    source.add_argument("--server", default=None,
                        help="verdict server URL, e.g. http://host:8000 (token from NOISESTOP_TOKEN)")
    p.add_argument("--criterion", choices=CRITERIA, default=None,
                   help=f"stopping criterion (default: model when --model, --server or --offset is "
                        f"given, else {DEFAULT_CRITERION}; README \"Deciding a stop\")")
    p.add_argument("--offset", type=_offset, default=None,
                   help="--criterion model: decision offset, the speed/accuracy knob (default: the "
                        "model's calibrated offset; larger stops later)")
    p.add_argument("--threshold", type=_threshold, default=None,
                   help="--criterion flip: c, the FLIP between the half buffers a block must reach "
                        "(default: the shipped calibration); --criterion variance: Blender Cycles' "
                        "noise threshold (default 0.01)")
    p.add_argument("--quantile", type=_fraction, default=1.0,
                   help="--criterion variance: fraction of a block's pixels that must pass (default: all)")
    p.add_argument("--reference", default=None,
                   help="labelled dataset or stack of the scene: oracle thresholds, early-stop metrics")
    p.add_argument("--exposure", type=_exposure, default=0.0,
                   help="display exposure (stops, -64..64) the criteria judge the image at (default 0)")
    p.add_argument("--time-limit", type=_float_in(0.0, 1e9, open_low=True), default=None, metavar="S",
                   help="stop after the pass under way at S seconds, writing the outputs and the "
                        "checkpoint (--resume continues)")
    p.add_argument("-D", dest="defines", type=_define, action="append", default=None, metavar="KEY=VALUE",
                   help="set a <default> parameter of an XML scene, as mitsuba -D does (repeatable), "
                        "e.g. -D integrator=path")
    # None = not given: taken from --reference, then the scene, then the defaults shown
    # (renderer/settings.py); the report's settings_source says which
    p.add_argument("--resolution", type=_resolution, default=None, metavar="N|WxH",
                   help="frame size: N scales the film's long side to N keeping its aspect ratio, WxH "
                        "sets both (default: the reference's, else the scene's own: 256x256 for "
                        "built-ins, the film of an XML file)")
    blocks = p.add_mutually_exclusive_group()
    blocks.add_argument("--block", type=_side, default=None, metavar="PX",
                        help="blocks of PX x PX pixels; edge blocks are full windows moved flush with "
                             "the frame's edge, overlapping their neighbour (default: the reference's "
                             "grid, else the block size of the training data, renderer.settings)")
    blocks.add_argument("--grid", type=_side, nargs=2, default=None, metavar=("ROWS", "COLS"),
                        help="blocks as a grid that divides the frame (default: the reference's)")
    p.add_argument("--min-spp", type=_spp, default=None,
                   help="first decision (default: the reference's first level, else 16)")
    p.add_argument("--max-spp", type=_spp, default=None,
                   help="most spp per block (default: the reference's last level, else 1024)")
    p.add_argument("--step", type=_spp, default=None,
                   help="spp added per pass (default: the reference's level step, else 16)")
    p.add_argument("--seed", type=_seed, default=0)
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.npz")
    p.add_argument("--checkpoint-every", type=_float_in(0.0, 1e9), default=30.0, metavar="S",
                   help="seconds between checkpoints (also written at the end, at --time-limit and on "
                        "Ctrl-C/SIGTERM); 0: after every pass (default 30)")
    _add_pool_arguments(p, ", for several scenes")
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_render)


def cmd_render(args: argparse.Namespace) -> int:
    from renderer.render_many import render_command
    from renderer.outputs import format_report
    from renderer.scenes import DEFAULT_SCENE

    criterion = args.criterion or ("model" if args.model or args.server or args.offset is not None
                                   else DEFAULT_CRITERION)
    try:
        result = render_command(
            args.scene or DEFAULT_SCENE, args.out, criterion=criterion, model=args.model,
            server=args.server, reference=args.reference, threshold=args.threshold,
            quantile=args.quantile, offset=args.offset, workers=args.workers, scheduler=args.scheduler,
            exposure=args.exposure,
            resolution=args.resolution, grid=None if args.grid is None else tuple(args.grid), block=args.block,
            checkpoint_every=args.checkpoint_every, step=args.step,
            min_spp=args.min_spp, max_spp=args.max_spp, seed=args.seed, resume=args.resume,
            defines=dict(args.defines) if args.defines else None, time_limit=args.time_limit)
    except ConnectionError as exc:      # verdict server unreachable or failing
        raise UsageError(str(exc)) from exc
    single = "blocks" in result         # one scene: its report; several: a summary
    if args.json:
        emit_json(result)
    elif single:
        print(format_report(result, args.out))
    else:
        for name, rep in result["scenes"].items():
            print(format_report(rep, f"{result['out']}/{name}"), end="\n\n")
    if not single:
        for scene, err in result["failed"].items():
            log.error("scene %s failed: %s", scene, err)
        return 1 if result["failed"] else 0
    return 0


def _register_serve(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="serve verdicts over HTTP (Open Inference Protocol v2)")
    p.add_argument("--model", action="append", default=None, metavar="[NAME=]PATH",
                   help="model bundle to serve, optionally under NAME; repeat for several (the "
                        "first is also served as 'default'); none: the bundled model")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on; anything but loopback needs a token")
    p.add_argument("--port", type=_int_in(0, 65535), default=8000)
    p.add_argument("--token-file", default=None,
                   help="file holding the bearer token (default: $NOISESTOP_TOKEN, "
                        "else the file $NOISESTOP_TOKEN_FILE names)")
    p.add_argument("--max-body-bytes", type=_int_in(1, 1 << 40), default=None,
                   help="largest request body (default: $NOISESTOP_MAX_BODY_BYTES or 64 MiB)")
    p.add_argument("--max-batch", type=_int_in(1, 1 << 20), default=None,
                   help="most blocks per request (default: $NOISESTOP_MAX_BATCH or 1024)")
    p.add_argument("--max-block-side", type=_int_in(MIN_SIDE, MAX_SIDE), default=None,
                   help="longest block side accepted, in pixels (default: $NOISESTOP_MAX_BLOCK_SIDE or "
                        "2048); larger blocks are refused with 413 before any work")
    p.add_argument("--max-pixels", type=_int_in(MIN_SIDE, 1 << 31), default=None,
                   help="pixels of one request, blocks x height x width (default: $NOISESTOP_MAX_PIXELS "
                        "or 4194304); over it: 413")
    p.add_argument("--memory-budget", type=_int_in(1 << 20, 1 << 44), default=None,
                   help="bytes of working memory all requests in flight may take together (default: "
                        "$NOISESTOP_MEMORY_BUDGET or what one request of --max-body-bytes takes, 16x its "
                        "body); a request waits for its share, then gets 503")
    p.add_argument("--threads", type=_int_in(1, 256), default=2,
                   help="requests classified at the same time")
    p.add_argument("--torch-threads", type=_int_in(1, 256), default=1,
                   help="torch threads for each request being classified (default 1: requests "
                        "already run --threads at a time)")
    p.add_argument("--limit-concurrency", type=_int_in(1, 65536), default=64,
                   help="most requests in flight; more are answered 503 with Retry-After (health "
                        "probes and /metrics are never refused; default 64)")
    p.add_argument("--max-connections", type=_int_in(1, 65536), default=1024,
                   help="most open connections, idle ones included (default 1024)")
    p.add_argument("--header-timeout", type=_seconds, default=10.0,
                   help="seconds a connection has to send a request's headers, from opening or from "
                        "its previous response (default 10; slow-header clients are closed)")
    p.add_argument("--body-timeout", type=_seconds, default=30.0,
                   help="seconds a request body may stall before a 408 (default 30)")
    p.add_argument("--keep-alive", type=_int_in(1, 3600), default=5,
                   help="seconds an idle kept-alive connection stays open (default 5)")
    p.add_argument("--offset", type=_offset, default=None,
                   help="decision offset for every model served (default: each model's calibrated "
                        f"offset; range +-{OFFSET_LIMIT:g}); a request's own 'offset' parameter overrides it")
    p.add_argument("--graceful-timeout", type=_seconds, default=30.0,
                   help="seconds SIGTERM waits for requests in flight")
    p.set_defaults(handler=cmd_serve)


def cmd_serve(args: argparse.Namespace) -> int:
    from service.serve import parse_model_specs, run
    run(parse_model_specs(args.model), args.host, args.port, token_file=args.token_file,
        max_body_bytes=args.max_body_bytes, max_batch=args.max_batch,
        inference_threads=args.threads, graceful_timeout=args.graceful_timeout, offset=args.offset,
        max_block_side=args.max_block_side, max_pixels=args.max_pixels,
        limit_concurrency=args.limit_concurrency, max_connections=args.max_connections,
        header_timeout=args.header_timeout, body_timeout=args.body_timeout, keep_alive=args.keep_alive,
        memory_budget=args.memory_budget, torch_threads=args.torch_threads)
    return 0


def cmd_scenes(args: argparse.Namespace) -> int:
    from renderer.scenes import list_scenes
    held = {n for n, _ in list_scenes(heldout=True)}
    scenes = list_scenes()
    if args.json:
        emit_json({"scenes": [{"name": n, "description": d, "heldout": n in held} for n, d in scenes]})
    else:
        width = max(len(n) for n, _ in scenes)
        for name, desc in scenes:
            print(f"{name:<{width}}  {'held out  ' if name in held else 'training  '}{desc}")
    return 0


def cmd_features(args: argparse.Namespace) -> int:
    import numpy as np

    from noisefeat import FEATURE_NAMES, extract_features, split_blocks
    from renderer.blocks import BlockRenderer
    from renderer.scenes import DEFAULT_SCENE, load_scene
    from learning.data.variant import select_variant

    _check_frame(args.resolution, args.resolution, tuple(args.grid), "--resolution/--grid")
    variant = select_variant()
    scene_name = args.scene or DEFAULT_SCENE
    t0 = time.perf_counter()
    scene = load_scene(scene_name, resolution=args.resolution)
    image = BlockRenderer(scene, grid=tuple(args.grid)).render_full(spp=args.spp, seed=0)
    t_render = time.perf_counter() - t0
    blocks = split_blocks(image, tuple(args.grid))
    t1 = time.perf_counter()
    feats, bad = extract_features(blocks, exposure=args.exposure, return_nonfinite=True)
    t_feat = time.perf_counter() - t1
    if args.json:
        emit_json({"scene": scene_name, "variant": variant, "spp": args.spp,
                   "resolution": list(image.shape[:2]), "feature_names": list(FEATURE_NAMES),
                   "features": np.round(feats, 6).tolist(), "nonfinite_pixels": bad.tolist(),
                   "render_s": t_render, "features_s": t_feat})
        return 0
    print(f"scene {scene_name}: {image.shape[1]}x{image.shape[0]}, {args.spp} spp, "
          f"{len(blocks)} blocks of {blocks.shape[2]}x{blocks.shape[1]}, variant {variant}")
    cols = ["blk"] + [n.replace("_", "") for n in FEATURE_NAMES]
    print(" ".join(f"{c:>7}" for c in cols))
    for i, row in enumerate(feats):
        print(f"{i:>7} " + " ".join(f"{v:7.3f}" for v in row))
    print(f"render {t_render * 1e3:.0f} ms (scene load + JIT included), "
          f"features {t_feat * 1e3:.1f} ms for {len(blocks)} blocks")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from pathlib import Path

    from .lab import bench
    unknown = sorted(set(args.what) - set(bench.SECTIONS))
    if unknown:
        raise UsageError(f"unknown bench sections {unknown}; known: {', '.join(bench.SECTIONS)}")
    arches = None if args.arches is None else tuple(a for a in args.arches.split(",") if a)
    kinds = None if args.kinds is None else tuple(k for k in args.kinds.split(",") if k)

    def update(name: str, markdown: str) -> None:   # section by section: ctrl-c loses nothing done
        bench.update_markdown(Path(args.update), {name: markdown})
        log.info("updated %s: section %s", args.update, name)
    results = bench.run_all(repeats=args.repeats, only=tuple(args.what), data=args.data,
                            out_dir=args.out, arches=arches, kinds=kinds, quick=args.quick,
                            on_section=update if args.update else None, heldout=args.heldout)
    if args.json:
        emit_json(results)
    else:
        print(bench.format_results(results))
    for name, why in results["failed"].items():
        log.error("bench %s not measured: %s", name, why)
    return 1 if results["failed"] else 0
