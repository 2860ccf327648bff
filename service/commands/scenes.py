"""`noisestop scenes` and `noisestop features`: the built-in scenes, and the 26 features of a
scene's blocks at low spp."""
from __future__ import annotations

import argparse
import time

from ..console import emit_json
from . import arguments as arg


def register_scenes(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("scenes", help="list the built-in scenes")
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_scenes)


def register_features(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("features", help="render a scene at low spp and print each block's 26 features")
    p.add_argument("--scene", default=None, help="built-in scene name or Mitsuba 3 XML file")
    p.add_argument("--resolution", type=arg.side, default=128)
    p.add_argument("--spp", type=arg.spp, default=16)
    p.add_argument("--grid", type=arg.side, nargs=2, default=(4, 4), metavar=("ROWS", "COLS"))
    p.add_argument("--exposure", type=arg.exposure, default=0.0)
    p.add_argument("--json", action="store_true")
    p.set_defaults(handler=cmd_features)


def cmd_scenes(args: argparse.Namespace) -> int:
    from renderer.scenes.catalog import list_scenes
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
    from noisefeat.blocks import grid_block_shape
    from renderer.live.blocks import BlockRenderer
    from renderer.scenes.catalog import DEFAULT_SCENE, load_scene
    from learning.data.variant import select_variant

    arg.check_frame(args.resolution, args.resolution, tuple(args.grid), "--resolution/--grid")
    variant = select_variant()
    scene_name = args.scene or DEFAULT_SCENE
    t0 = time.perf_counter()
    scene = load_scene(scene_name, resolution=args.resolution)
    br = BlockRenderer(scene, grid=tuple(args.grid))
    grid_block_shape((br.height, br.width), tuple(args.grid))     # before rendering: a scene file's aspect
    image = br.render_full(spp=args.spp, seed=0)
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
