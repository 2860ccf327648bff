"""`noisestop train`, `calibrate` and `pretrain`: fitting a model, flip's c, the feature base's
conv layers, on training scenes only.

None of them writes into the installed package unless given `--update-package` (the
maintainer's flag; `make model` uses it): `train` writes the bundle directory `--out`,
`calibrate` and `pretrain` write `--out` or, without it, the user data directory, where the
readers find the files before the shipped ones (`noisefeat.userdata`)."""
from __future__ import annotations

import argparse
import os
from pathlib import Path

from noisefeat.atomic import atomic_write
from noisefeat.userdata import UPDATE_PACKAGE, user_file
from learning.names import DEFAULT_INPUT, DEFAULT_TAU, MODEL_KINDS, QUICK_MODES, TRANSFER_INPUTS, TRANSFER_KINDS

from renderer.settings import DEFAULT_TILE

from ..console import UsageError, emit_json
from . import arguments as arg


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train a model on a dataset (scenes held out for evaluation)")
    p.add_argument("--data", required=True, help="dataset directory")
    p.add_argument("--model", default="dsvm_as", choices=MODEL_KINDS,
                   help="model kind (default dsvm_as); vgg19 ... densenet201: a transfer baseline "
                        "(frozen conv base + the paper's head, docs/guide/training.md)")
    p.add_argument("--weights", default=None, metavar="FILE",
                   help="transfer baselines: a local ImageNet state_dict for the base (never downloaded; "
                        "default: the torch hub cache, else an untrained base, labelled so)")
    _destination(p, "model bundle directory to write", "bundle learning/bundled", required=True)
    p.add_argument("--test-scenes", default=None,
                   help="comma-separated scenes of --data held out of training ('' for none; default: "
                        "every 4th by name, none with --heldout)")
    p.add_argument("--heldout", default=None, metavar="DIR",
                   help="labelled dataset of held-out scenes to report on (then every scene of --data "
                        "is trained on, unless --test-scenes says otherwise)")
    p.add_argument("--initial-scene", default=None, help="active kinds: the initially labelled scene(s), comma-separated (default: the "
                        "scenes closest to half converged, at least 500 sub-images)")
    p.add_argument("--label-budget", type=arg.fraction, default=0.25,
                   help="active kinds: largest fraction of the pool's labels to query")
    p.add_argument("--no-cv", action="store_true", help="skip the C/gamma cross-validation")
    p.add_argument("--max-early-stop", type=arg.rate, default=0.05,
                   help="calibrate the decision offset on leave-one-scene-out scores of the "
                        "training scenes to keep early stops at or below this rate (default 0.05)")
    p.add_argument("--no-calibrate", action="store_true", help="keep the decision offset at 0")
    p.add_argument("--input", "--quick", dest="quick", choices=QUICK_MODES, default=DEFAULT_INPUT,
                   help="feature models' input: halves (noise features of the half buffers next to "
                        "features of the block, docs/guide/training.md), or the paper's quick image "
                        "subtracted from the features: the albedo AOV, direct lighting, or none (a "
                        f"flat image: features of the current block alone); default {DEFAULT_INPUT}. "
                        "Transfer baselines: halves (the displayed noise picture of the half buffers) "
                        "or none (the block itself, the paper's)")
    p.add_argument("--composition", default=None,
                   help="input halves: which parts of the half-buffer input a feature model reads, "
                        "joined by '+' (n noise, c current, r ratios, l luminance, f FLIP; "
                        "docs/guide/training.md; default: the measured best, learning.inputs.noise_input.HALVES)")
    p.add_argument("--seed", type=arg.seed, default=0)
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_train)

    p = sub.add_parser("calibrate", help="calibrate the flip criterion's c on training scenes, or train and "
                                         "calibrate the estimate criterion's bundle")
    p.add_argument("--data", required=True, help="labelled dataset of training scenes (never held-out ones)")
    p.add_argument("--criterion", choices=("flip", "estimate"), default="flip",
                   help="flip: c(tau) for the halves' score; estimate: the learned per-tile error estimate "
                        "and its c(tau), written as a bundle directory (docs/guide/training.md)")
    p.add_argument("--kind", choices=("gbm", "linear"), default="gbm",
                   help="estimate only: boosted trees or a ridge line (default gbm)")
    p.add_argument("--quantile", type=arg.float_in(0.0, 1.0), default=None,
                   help="estimate only: learn this quantile of the correction (the trees' pinball loss: each "
                        "tile its own margin) instead of its mean")
    p.add_argument("--max-early-stop", type=arg.rate, default=0.05,
                   help="largest early-stop rate accepted on the training scenes (default 0.05)")
    p.add_argument("--min-spp", type=arg.spp, default=None,
                   help="no decision below this many spp (default: from the first level)")
    p.add_argument("--tile", type=arg.int_in(0, 4096), default=DEFAULT_TILE, metavar="PX",
                   help=f"also calibrate c(tau) per tile of PX pixels, on the tiles' history, against the "
                        f"blocks the final frame leaves above tau (default {DEFAULT_TILE}, the render's; 0: blocks only)")
    _destination(p, "calibration file to write (default: flip.json in the user data directory, which the "
                    "flip criterion then reads instead of the shipped one; estimate: the bundle directory, "
                    "default estimate/ there)", "learning/flip.json or learning/bundled_estimate")
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_calibrate)

    p = sub.add_parser("pretrain", help="pre-train the feature base's conv layers as a denoiser")
    p.add_argument("--data", required=True, help="dataset directory (training scenes only are used)")
    _destination(p, "safetensors file to write (default: weights/pretrained.safetensors in the user data "
                    "directory, which the weight name 'pretrained' then finds first)",
                 "noisefeat/weights/pretrained.safetensors")
    p.add_argument("--test-scenes", default=None, help="scenes to keep out (default: every 4th by name)")
    p.add_argument("--steps", type=arg.int_in(1, 1_000_000), default=400)
    p.add_argument("--lr", type=arg.float_in(0.0, 10.0, open_low=True), default=0.003)
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_pretrain)


def _destination(p: argparse.ArgumentParser, out_help: str, shipped: str, required: bool = False) -> None:
    """--out PATH, or the maintainer's --update-package (rewrite the file that ships with the
    package): never both, and without either nothing in the package is written."""
    out = p.add_mutually_exclusive_group(required=required)
    out.add_argument("--out", default=None, help=out_help)
    out.add_argument(UPDATE_PACKAGE, action="store_true", help=f"maintainers: rewrite the shipped {shipped}")


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
    from learning.evaluation.evaluate import evaluate_model
    from learning.inputs.table import load_table
    from learning.models.bundle import BUNDLED_DIR, Model, save_model
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
    if args.update_package:
        args.out = str(BUNDLED_DIR)
    raw = args.model.startswith("svm")
    opts = {"image": True, "quick": args.quick} if transfer else \
        {"raw": raw, "quick": args.quick, **_composition(args, raw)}
    table = load_table(args.data, **opts)
    if not 0 <= args.max_early_stop <= 1:
        raise UsageError(f"--max-early-stop must be in [0, 1], got {args.max_early_stop}")
    test_scenes = [] if args.test_scenes == "" else arg.scene_list(args.test_scenes)   # '': none
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
    summary["tau"] = DEFAULT_TAU            # the observer's tau of the labels it was trained on
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
    from renderer.scenes.catalog import list_scenes
    try:
        check_disjoint(scenes, [n for n, _ in list_scenes(heldout=True)])
    except ValueError as exc:
        raise UsageError(f"{what}: {exc} (renderer/scenes/heldout.py)") from None


def cmd_calibrate(args: argparse.Namespace) -> int:
    import datetime
    import json

    from learning.data.dataset_dir import dataset_fingerprint, read_stacks
    from learning.evaluation.calibrate import calibrate_flip_curve
    from learning.inputs.halves import FLIP_CALIBRATION, FLIP_USER_FILE

    if not 0 <= args.max_early_stop <= 1:
        raise UsageError(f"--max-early-stop must be in [0, 1], got {args.max_early_stop}")
    stacks = read_stacks(args.data)
    if not stacks:
        raise UsageError(f"{args.data}: no stacks found")
    _refuse_heldout([s.scene for s in stacks], "calibrate")
    if args.criterion == "estimate":
        return _calibrate_estimate(args, stacks)
    cal = calibrate_flip_curve(stacks, args.max_early_stop, min_spp=args.min_spp)
    if args.tile:                # the same, per tile against the tile truth (the live loop's default grain)
        part = calibrate_flip_curve(stacks, args.max_early_stop, min_spp=args.min_spp, tile=args.tile)
        cal["tiles"] = {str(args.tile): {k: part[k] for k in ("unit", "curve", "c", "target_early_stop_rate",
                                                              "statistic", "tile_truth", "rate")}}
    cal.update(criterion="flip", data=str(args.data), fingerprint=dataset_fingerprint(args.data),
               observer={"ppd": 67, "display": "clip+srgb", "pooling": cal["pooling"]},
               calibrated=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"))
    out = Path(args.out) if args.out else FLIP_CALIBRATION if args.update_package else user_file(FLIP_USER_FILE)
    atomic_write(out, json.dumps(cal, indent=1, default=float) + "\n")
    points = cal["curve"]
    if args.json:
        emit_json({"out": str(out), "pooling": cal["pooling"], "curve": [
            {k: p["chosen"][k] if k in p["chosen"] else p[k] for k in ("tau", "c", "early_stop_rate",
                                                                     "spp_ratio_vs_oracle")} for p in points]})
    else:
        for unit, part in (("block", cal), *((f"tile{t}", c) for t, c in cal.get("tiles", {}).items())):
            for p in part["curve"]:
                print(f"flip per {unit}: tau {p['tau']:<7g} c = {p['c']:<8.5g} on {len(stacks)} training scenes: "
                      f"early stops {p['chosen']['early_stop_rate']:.3f} (target {args.max_early_stop:g}), "
                      f"samples {p['chosen']['spp_ratio_vs_oracle']:.3f} x oracle")
        print(f"wrote {out}")
    return 0


def _calibrate_estimate(args: argparse.Namespace, stacks: list) -> int:
    """`calibrate --criterion estimate`: train the per-tile error estimate on the stacks,
    choose its c(tau) out of fold, write the bundle."""
    from learning.data.dataset_dir import dataset_fingerprint
    from learning.models.tile_error_bundle import BUNDLED_DIR, USER_DIR, save_tile_error_bundle
    from learning.training.train_estimate import train_tile_error

    if args.min_spp is not None:
        raise UsageError("--min-spp applies to --criterion flip only")
    tile = args.tile or DEFAULT_TILE
    if args.quantile is not None and not 0 < args.quantile < 1:
        raise UsageError(f"--quantile must be in (0, 1), got {args.quantile}")
    if args.quantile is not None and args.kind != "gbm":
        raise UsageError("--quantile is learned by --kind gbm only")
    params = {"kind": args.kind, **({} if args.quantile is None else {"quantile": args.quantile})}
    estimator, cal, record = train_tile_error(stacks, tile=tile, params=params,
                                              max_early_stop=args.max_early_stop)
    record.update(data=str(args.data), fingerprint=dataset_fingerprint(args.data))
    out = Path(args.out) if args.out else BUNDLED_DIR if args.update_package else user_file(USER_DIR)
    save_tile_error_bundle(estimator, out, tile=tile, calibration=cal, training=record)
    if args.json:
        emit_json({"out": str(out), "rows": record["rows"], "curve": [{"tau": p["tau"], "c": p["c"]}
                                                                       for p in cal["curve"]],
                   "out_of_fold_spread": record["out_of_fold_spread"]})
    else:
        for p in cal["curve"]:
            print(f"estimate per tile{tile}: tau {p['tau']:<7g} c = {p['c']:.5g}")
        spread = record["out_of_fold_spread"]
        print(f"{record['rows']} rows from {len(stacks)} training scenes; out-of-fold spread s "
              f"{spread['estimate']:.3f} (the halves' history: {spread['halves_history']:.3f}); wrote {out}")
    return 0


def cmd_pretrain(args: argparse.Namespace) -> int:
    from learning.models.pretrain import pretrain_base
    from learning.data.dataset_dir import read_stacks
    from learning.evaluation.generalisation import default_test_scenes
    from noisefeat.weights import PRETRAINED_FILE, PRETRAINED_USER_FILE, save_kernels

    stacks = read_stacks(args.data)
    held = set(arg.scene_list(args.test_scenes) or default_test_scenes([s.scene for s in stacks]))
    train = [s for s in stacks if s.scene not in held]
    base, report = pretrain_base(train, steps=args.steps, lr=args.lr)
    out = Path(args.out) if args.out else PRETRAINED_FILE if args.update_package else user_file(PRETRAINED_USER_FILE)
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
