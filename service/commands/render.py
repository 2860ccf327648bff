"""`noisestop render`: the adaptive progressive render of one scene or many.

A thin layer on the in-memory loop (`renderer.adaptive.run_adaptive`, which
`renderer.render` also runs): the command adds the output folder, checkpoints and
`--resume`, and several scenes on a pool."""
from __future__ import annotations

import argparse
import contextlib
from typing import Any

from learning.names import DEFAULT_TAU
from renderer.settings import MAX_TIME_LIMIT
from renderer.names import CRITERIA, DEFAULT_CRITERION, criterion_name

from ..console import UsageError, emit_json, log
from . import arguments as arg


def register(sub: argparse._SubParsersAction) -> None:
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
    p.add_argument("--offset", type=arg.offset, default=None,
                   help="--criterion model: decision offset, the speed/accuracy knob (default: the "
                        "model's calibrated offset; larger stops later)")
    p.add_argument("--threshold", type=arg.threshold, default=None,
                   help="--criterion flip: c, the FLIP between the half buffers a block must reach "
                        "(default: c(tau) of the shipped calibration); --criterion variance: Blender Cycles' "
                        "noise threshold (default 0.01)")
    p.add_argument("--tau", type=arg.tau, default=DEFAULT_TAU, help=arg.TAU_HELP)
    p.add_argument("--quantile", type=arg.fraction, default=1.0,
                   help="--criterion variance: fraction of a block's pixels that must pass (default: all)")
    p.add_argument("--reference", default=None,
                   help="labelled dataset or stack of the scene (oracle thresholds, early-stop metrics, "
                        "final_vs_reference), or a reference image FILE.exr of the render's size "
                        "(final_vs_reference only)")
    p.add_argument("--exposure", type=arg.exposure, default=0.0,
                   help="display exposure (stops, -64..64) the criteria judge the image at (default 0)")
    p.add_argument("--time-limit", type=arg.float_in(0.0, MAX_TIME_LIMIT, open_low=True), default=None,
                   metavar="S", help="stop after the pass under way at S seconds, writing the outputs and the "
                        "checkpoint (--resume continues); when the time will not cover every block, "
                        "passes go to the blocks farthest from the noise target first")
    p.add_argument("--spp-budget", type=arg.float_in(0.0, arg.MAX_SPP, open_low=True), default=None, metavar="N",
                   help="samples per pixel to spend, averaged over the blocks: each pass goes to the "
                        "blocks farthest from the noise target; report.json lists (and spp_map.png "
                        "outlines) the blocks still above it when the budget ends. --time-limit "
                        "spends its seconds the same way")
    p.add_argument("-D", dest="defines", type=arg.define, action="append", default=None, metavar="KEY=VALUE",
                   help="set a <default> parameter of an XML scene, as mitsuba -D does (repeatable), "
                        "e.g. -D integrator=path")
    # None = not given: taken from --reference, then the scene, then the defaults shown
    # (renderer/settings.py); the report's settings_source says which
    p.add_argument("--resolution", type=arg.resolution, default=None, metavar="N|WxH",
                   help="frame size: N scales the film's long side to N keeping its aspect ratio, WxH "
                        "sets both (default: the reference's, else the scene's own: 256x256 for "
                        "built-ins, the film of an XML file)")
    blocks = p.add_mutually_exclusive_group()
    blocks.add_argument("--block", type=arg.side, default=None, metavar="PX",
                        help="blocks of PX x PX pixels; edge blocks are full windows moved flush with "
                             "the frame's edge, overlapping their neighbour (default: the reference's "
                             "grid, else the block size of the training data, renderer.settings)")
    blocks.add_argument("--grid", type=arg.side, nargs=2, default=None, metavar=("ROWS", "COLS"),
                        help="blocks as a grid that divides the frame (default: the reference's)")
    p.add_argument("--min-spp", type=arg.spp, default=None,
                   help="first decision (default: the reference's first level, else 16)")
    p.add_argument("--max-spp", type=arg.spp, default=None,
                   help="most spp per block (default: the reference's last level, else 1024)")
    p.add_argument("--step", type=arg.spp, default=None,
                   help="spp added per pass (default: the reference's level step, else 16)")
    p.add_argument("--seed", type=arg.seed, default=0)
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.npz")
    p.add_argument("--checkpoint-every", type=arg.float_in(0.0, 1e9), default=30.0, metavar="S",
                   help="seconds between checkpoints (also written at the end, at --time-limit and on "
                        "Ctrl-C/SIGTERM); 0: after every pass (default 30)")
    arg.add_pool_arguments(p, ", for several scenes")
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_render)


def cmd_render(args: argparse.Namespace) -> int:
    from renderer.render_many import render_command
    from renderer.outputs import format_report
    from renderer.outlock import locked_output

    criterion = criterion_name(args.criterion, model=args.model, server=args.server, offset=args.offset)
    try:       # --out is locked for the render's lifetime (renderer.outlock)
        lock = locked_output(args.out) if args.out else contextlib.nullcontext()
        with lock:
            result = _render(args, criterion, render_command)
    except ConnectionError as exc:      # verdict server unreachable or failing
        raise UsageError(str(exc)) from exc
    return _print_result(args, result, format_report)


def _render(args: argparse.Namespace, criterion: str, render_command: Any) -> dict[str, Any]:
    from renderer.scenes import DEFAULT_SCENE
    return render_command(
        args.scene or DEFAULT_SCENE, args.out, criterion=criterion, model=args.model,
        server=args.server, reference=args.reference, threshold=args.threshold,
        quantile=args.quantile, offset=args.offset, workers=args.workers, scheduler=args.scheduler,
        exposure=args.exposure, tau=args.tau,
        resolution=args.resolution, grid=None if args.grid is None else tuple(args.grid), block=args.block,
        checkpoint_every=args.checkpoint_every, step=args.step,
        min_spp=args.min_spp, max_spp=args.max_spp, seed=args.seed, resume=args.resume,
        defines=dict(args.defines) if args.defines else None, time_limit=args.time_limit,
        spp_budget=args.spp_budget)


def _print_result(args: argparse.Namespace, result: dict[str, Any], format_report: Any) -> int:
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
