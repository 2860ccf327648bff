"""The golden renders of the pass loop: tiny fixture renders whose stops per block and image
were recorded with the host loop (numpy accumulators, one pass per launch) on llvm_ad_rgb,
so tests/renderer/test_device_loop.py (and benchmarks/device_checks.py on a GPU) can hold
the device loop to the same result.

    python -m tests.support.passloop_golden tests/fixtures/passloop_golden.npz

was run once, on the loop being replaced (the commit before the device loop); the file is
committed (about 0.3 MB). Running it now records the current loop instead."""
from __future__ import annotations

import sys

import numpy as np

import renderer

#: tau of the flip cases: 1 puts the dot guard's level (2.5 tau on the display) above any
#: pixel's error, so they hold the loop to the recording made before the guard existed
#: (the guard itself: tests/noisefeat/test_dots.py)
NO_DOTS = 1.0
#: (name, scene, keyword arguments of renderer.render)
CASES = (
    ("cornell_flip", "cornell", {"criterion": "flip", "tau": NO_DOTS, "threshold": 0.2, "resolution": 64, "block": 16, "step": 4, "min_spp": 8,
                                 "max_spp": 96}),
    ("cornell_variance", "cornell", {"criterion": "variance", "threshold": 0.15, "resolution": 64, "block": 16, "step": 4,
                                     "min_spp": 8, "max_spp": 96}),
    ("small_light_flip", "small_light", {"criterion": "flip", "tau": NO_DOTS, "threshold": 0.2, "resolution": 64, "block": 16, "step": 4,
                                         "min_spp": 8, "max_spp": 96}),
    ("overlap_flip", "cornell", {"criterion": "flip", "tau": NO_DOTS, "threshold": 0.2, "resolution": 72, "block": 32, "step": 4, "min_spp": 8,
                                 "max_spp": 64}),
    ("studio_flip", "studio_preview", {"criterion": "flip", "tau": NO_DOTS, "threshold": 0.2, "resolution": 64, "block": 16, "step": 4,
                                       "min_spp": 8, "max_spp": 64}),
    ("cbox_gaussian", "mitsuba:cornell_box", {"criterion": "flip", "tau": NO_DOTS, "threshold": 0.2, "block": 16, "step": 4,
                                              "min_spp": 8, "max_spp": 64}),
    ("cornell_budget", "cornell", {"criterion": "flip", "tau": NO_DOTS, "threshold": 0.05, "resolution": 64, "block": 16, "step": 4, "min_spp": 8,
                                   "max_spp": 96, "spp_budget": 24}),
)


def load(scene: str):
    """A case's scene: a built-in name, or "mitsuba:cornell_box" (Mitsuba's own Cornell box
    dict at 64x64, whose film has a Gaussian filter: the splatting path)."""
    if not scene.startswith("mitsuba:"):
        return scene
    import mitsuba as mi

    renderer.register()
    d = mi.cornell_box()
    d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = 64
    return mi.load_dict(d)


def render_case(case: str, grow: bool = True):
    """One golden case rendered by the current loop (`run_adaptive`, grown passes or a
    fixed step): its `RenderResult`, to hold against the recorded stops and image."""
    from renderer.adaptive import run_adaptive
    from renderer.criteria import make_criterion

    _, scene, kw = next(c for c in CASES if c[0] == case)
    crit = make_criterion(kw["criterion"], tau=kw.get("tau", 0.02), threshold=kw.get("threshold"))
    return run_adaptive(load(scene), crit, progress=False, grow=grow,
                        **{k: v for k, v in kw.items() if k not in ("criterion", "threshold", "tau")})


def main(out: str) -> None:
    arrays = {}
    for name, scene, kw in CASES:
        r = renderer.render(load(scene), progress=False, **kw)
        arrays[f"{name}/image"] = r.image
        arrays[f"{name}/block_spp"] = np.array([b["spp"] for b in r.report["blocks"]], np.int64)
        arrays[f"{name}/converged"] = np.array([b["converged"] for b in r.report["blocks"]], bool)
        print(name, r.report["variant"], arrays[f"{name}/block_spp"].tolist())
    np.savez_compressed(out, **arrays)


if __name__ == "__main__":
    main(sys.argv[1])
