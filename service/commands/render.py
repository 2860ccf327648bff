"""`noisestop render`: the adaptive progressive render of one scene or many.

A thin layer on the in-memory loop (`renderer.live.adaptive.run_adaptive`, which
`renderer.render` also runs): the command adds the output folder, checkpoints and
`--resume`, and several scenes on a pool."""
from __future__ import annotations

import argparse
from typing import Any

from renderer.setting_kinds import CLI
from renderer.settings import ROWS

from ..console import UsageError, emit_json, log
from . import arguments as arg


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("render", help="adaptive progressive render: stop sampling blocks that look converged")
    p.add_argument("--scene", default=None,
                   help="built-in scene name or Mitsuba 3 XML file; several comma-separated (default: cornell)")
    p.add_argument("--out", required=True, help="output directory (several scenes: one sub-directory each)")
    p.add_argument("--reference", default=None,
                   help="labelled dataset or stack of the scene (oracle thresholds, early-stop metrics, "
                        "final_vs_reference; its grid and levels become the defaults), or a reference image "
                        "FILE.exr of the render's size (final_vs_reference only)")
    # the render spec's rows (renderer/settings.py): None = not given, then the reference, the
    # scene and the defaults; the report's settings_source says which
    add_arguments(p)
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.npz")
    arg.add_pool_arguments(p, ", for several scenes")
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_render)


def cmd_render(args: argparse.Namespace) -> int:
    from renderer.live.outlock import locked_output
    from renderer.live.outputs import format_report
    from renderer.render_many import render_command
    from renderer.scenes.catalog import DEFAULT_SCENE

    if args.scene is not None and not args.scene.strip(" ,"):
        raise UsageError(f"--scene is empty ({args.scene!r}): name a built-in scene or an XML file "
                         f"(left out, it is {DEFAULT_SCENE})")
    try:       # --out is locked for the render's lifetime (renderer.live.outlock)
        with locked_output(args.out):       # an empty --out or / is refused there, in one line
            scenes = DEFAULT_SCENE if args.scene is None else args.scene
            result = render_command(scenes, args.out, given_from_args(args),
                                    reference=args.reference, workers=args.workers, scheduler=args.scheduler,
                                    resume=args.resume)
    except ConnectionError as exc:      # verdict server unreachable or failing
        raise UsageError(str(exc)) from exc
    return _print_result(args, result, format_report)


#: exit status of a render that finished but whose image holds pixels with no finite
#: sample (report.json nonfinite.pixels > 0): distinct, so a farm can tell it apart
NONFINITE_EXIT = 3


def _print_result(args: argparse.Namespace, result: dict[str, Any], format_report: Any) -> int:
    from renderer.live.report import nonfinite_line

    single = "blocks" in result         # one scene: its report; several: a summary
    reports = [result] if single else list(result["scenes"].values())
    if args.json:
        emit_json(result)
    else:
        outs = [args.out] if single else [f"{result['out']}/{name}" for name in result["scenes"]]
        for rep, out in zip(reports, outs):
            line = nonfinite_line(rep)   # the summary says it too (the renderer warned on stderr)
            print(format_report(rep, out) + (f"\n{line}" if line else ""), end="\n" if single else "\n\n")
    if not single:
        for scene, err in result["failed"].items():
            log.error("scene %s failed: %s", scene, err)
        if result["failed"]:
            return 1
    return NONFINITE_EXIT if any((r.get("nonfinite") or {}).get("pixels") for r in reports) else 0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The command line's flags for the render spec's rows it offers: each row's own
    (`Row.cli_options`: its type, metavar and help; the combinations, such as grid with
    block, are `resolve`'s to refuse)."""
    for row in ROWS:
        if CLI in row.doors:
            parser.add_argument(row.flag, dest=row.name, **row.cli_options())


def given_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """What the command line gave, row by row (None: not given)."""
    return {r.name: r.from_cli(getattr(args, r.name, None)) for r in ROWS if CLI in r.doors}
