"""`noisestop dataset build|import-lisic|check`: labelled datasets."""
from __future__ import annotations

import argparse

from noisefeat.bounds import MIN_SIDE
from noisefeat.pooling import DEFAULT_POOLING, POOLINGS
from renderer.settings import MAX_SPP

from ..console import UsageError, emit_json, log
from . import arguments as arg


def register(sub: argparse._SubParsersAction) -> None:
    ds = sub.add_parser("dataset", help="build, import and check labelled datasets")
    dsub = ds.add_subparsers(dest="dataset_command", metavar="ACTION", required=True)

    p = dsub.add_parser("build", help="render and label stacks (format v1) for scenes")
    p.add_argument("--out", required=True, help="dataset directory (one sub-directory per scene)")
    p.add_argument("--scenes", default=None,
                   help="comma-separated built-in names, XML files, procedural scenes (proc-0042, or "
                        "procedural:N for the first N, procedural:A-B for seeds A..B-1), or the sets "
                        "'training' (the training library, the default) and 'heldout' (scenes kept out "
                        "of all training)")
    p.add_argument("--resolution", type=arg.side, default=512)
    p.add_argument("--block", type=arg.int_in(MIN_SIDE, arg.MAX_SIDE), default=None,
                   help="block side in pixels (default: a 4x4 grid, the paper's); must divide --resolution")
    p.add_argument("--step", type=arg.spp, default=101, help="spp added per level")
    p.add_argument("--levels", type=arg.int_in(1, 100_000), default=100)
    p.add_argument("--reference-spp", type=arg.spp, default=None,
                   help="default: 4 x the last level")
    p.add_argument("--seed", type=arg.seed, default=0)
    p.add_argument("--tau", type=arg.fraction, default=0.02, help="virtual observer threshold on FLIP")
    p.add_argument("--no-contact-sheets", action="store_true")
    arg.add_pool_arguments(p, "")
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_dataset_build)

    p = dsub.add_parser("import-lisic", help="import a dataset in the LISIC layout")
    p.add_argument("src")
    p.add_argument("--out", required=True)
    p.add_argument("--every", type=arg.int_in(1, 1_000_000), default=1, help="keep one image in EVERY")
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_import_lisic)

    p = dsub.add_parser("relabel", help="relabel virtual-observer stacks by the current observer (no rendering)")
    p.add_argument("dir")
    p.add_argument("--pooling", choices=POOLINGS, default=DEFAULT_POOLING,
                   help="how a block's FLIP map is pooled (default %(default)s: the largest 16x16 tile mean; "
                        "'mean': the first observer's block mean, for comparison)")
    p.add_argument("--tau", type=arg.tau, default=None,
                   help="noise target of the new labels (default: each stack's own)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_dataset_relabel)

    p = dsub.add_parser("check", help="validate a dataset and report every problem found")
    p.add_argument("dir")
    p.add_argument("--quick", action="store_true", help="skip reading the images")
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_dataset_check)


def cmd_dataset_build(args: argparse.Namespace) -> int:
    from renderer.dataset.build import build_dataset
    from renderer.scenes.procedural import expand_procedural
    from renderer.scenes.catalog import list_scenes
    from renderer.dataset.stackbuild import BuildSettings

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
    arg.check_frame(args.resolution, args.resolution, grid, "--resolution/--block")
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


def cmd_dataset_relabel(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from learning.data.dataset_dir import list_stacks
    from learning.data.relabel import relabel_if_stale
    from learning.data.stack import read_stack

    paths = list_stacks(args.dir)
    if not paths:
        raise UsageError(f"{args.dir}: no stacks found (no meta.json below it)")
    rows = []
    for p in tqdm(paths, desc="relabel", unit="stack", leave=False):
        before = read_stack(p)
        after, changed = relabel_if_stale(before, args.pooling, args.tau)
        rows.append({"scene": after.scene, "relabelled": changed, "labeler": (after.labeler or {}).get("name"),
                     "before": before.thresholds, "after": after.thresholds})
    if args.json:
        emit_json({"dir": str(args.dir), "pooling": args.pooling, "stacks": rows})
    else:
        for r in rows:
            what = "relabelled" if r["relabelled"] else ("kept (its own labels: " + str(r["labeler"]) + ")"
                                                         if r["labeler"] != "flip" else "already current")
            moved = sum(a != b for a, b in zip(r["before"] or [], r["after"] or []))
            print(f"{r['scene']:<16} {what}" + (f": {moved} of {len(r['after'] or [])} thresholds moved"
                                              if r["relabelled"] else ""))
        print(f"{args.dir}: {sum(r['relabelled'] for r in rows)} of {len(rows)} stacks relabelled "
              f"({args.pooling})")
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
