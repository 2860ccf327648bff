"""The golden renders of the pass loop: tiny fixture renders whose stops per block and image
were recorded with the host loop (numpy accumulators, one pass per launch) on llvm_ad_rgb,
so tests/renderer/test_device_loop.py (and benchmarks/device_checks.py on a GPU) can hold
the device loop to the same result.

    python -m tests.support.passloop_golden record tests/fixtures/passloop_golden.npz

was run once, on the loop being replaced (the commit before the device loop), on an Intel
Xeon; the file is committed (about 0.3 MB). Running it now records the current loop instead.

**What holds on another CPU.** Dr.Jit's LLVM backend compiles for the CPU it
runs on (vector width, FMA contraction, order of sums), so the path tracer's float32
arithmetic rounds differently on another CPU: the image is held to `IMAGE_RTOL`
(`image_mismatch`), not bit for bit. The stops are held exactly, which is sound only where
no decision sat within rounding of its threshold: `DecisionLog` records, at every decision,
each asked block's score over its threshold and the flat test's display range over its
tolerance, and, in budget renders, each round's priorities against the band; its `margin`
must clear `MARGIN`. `set_llvm_target` (env NOISESTOP_TEST_LLVM_TARGET, applied by
tests/conftest.py) makes this CPU generate another CPU's code: `make test-portability`
runs the suite so, after `shift`, which prints per case how far pixels and decisions moved:

    python -m tests.support.passloop_golden shift haswell,8
"""
from __future__ import annotations

import ctypes
import os
import sys
from dataclasses import dataclass, field
from typing import Any

import numpy as np

import renderer

#: tau of the flip cases: 1 puts the dot guard's level (2.5 tau on the display) above any
#: pixel's error, so they hold the loop to the recording made before the guard existed
#: (the guard itself: tests/noisefeat/test_dots.py)
NO_DOTS = 1.0
#: (name, scene, keyword arguments of renderer.render)
#: the recorded cases: block grain (tile = block) and every unit near its target
#: judged at each pass (decide_growth 0: `renderer.live.passloop.next_decision`), as when
#: they were recorded; the growth floor's own tests: tests/renderer/test_decide_growth.py
CASES = tuple((name, scene, {**kw, "decide_growth": 0.0}) for name, scene, kw in (
    ("cornell_flip", "cornell", {"criterion": "flip", "tau": NO_DOTS, "threshold": 0.2, "resolution": 64, "block": 16, "step": 4, "min_spp": 8,
                                 "max_spp": 96}),
    ("cornell_variance", "cornell", {"criterion": "variance", "threshold": 0.15, "resolution": 64, "block": 16, "step": 4,
                                     "min_spp": 8, "max_spp": 96}),
    ("small_light_flip", "small_light", {"criterion": "flip", "tau": NO_DOTS, "threshold": 0.2, "resolution": 64, "block": 16, "step": 4,
                                         "min_spp": 8, "max_spp": 96}),
    ("overlap_flip", "cornell", {"criterion": "flip", "tau": NO_DOTS, "threshold": 0.2, "resolution": 72, "block": 32, "tile": 32,
                                 "step": 4, "min_spp": 8, "max_spp": 64}),
    ("studio_flip", "studio_preview", {"criterion": "flip", "tau": NO_DOTS, "threshold": 0.2, "resolution": 64, "block": 16, "step": 4,
                                       "min_spp": 8, "max_spp": 64}),
    ("cbox_gaussian", "mitsuba:cornell_box", {"criterion": "flip", "tau": NO_DOTS, "threshold": 0.2, "block": 16, "step": 4,
                                              "min_spp": 8, "max_spp": 64}),
    ("cornell_budget", "cornell", {"criterion": "flip", "tau": NO_DOTS, "threshold": 0.05, "resolution": 64, "block": 16, "step": 4, "min_spp": 8,
                                   "max_spp": 96, "spp_budget": 24}),
))

#: The image bound, relative per pixel: 4096 float32 ulps (2^-24 each), 2.4e-4. Why this
#: much: a pixel is a mean of path samples, each the end of a chain of float32 operations
#: (intersections, frames, BSDF and light sampling and evaluation at every bounce: on the
#: order of a thousand operations on these scenes). Another instruction set rounds each of
#: them differently by at most an ulp, so a sample moves by at most about (operations) ulps,
#: relative; radiance samples are non-negative, so their mean moves by no more, relatively,
#: and the accumulators sum in float64. Measured: 4.8e-5 at worst between AVX-512 and AVX2
#: code on one AMD EPYC (`make test-portability`), 5.5e-5 between an Intel Xeon and an AMD
#: EPYC. Why that is enough to catch a wrong loop: one pass of n added twice or
#: dropped moves a pixel by (pass - mean) / n, the noise of one 4-spp pass over n <= 24,
#: percents, a hundred times the bound (the controls in tests/renderer/test_device_loop.py).
IMAGE_RTOL = 2.0 ** -12
#: below this (linear radiance) a pixel is compared absolutely: black stays black
IMAGE_ATOL = 1e-9
#: The smallest relative distance of a decision's quantity from its threshold that keeps the
#: stops the same on any CPU: IMAGE_RTOL, the pixels' own bound. A decision's quantity is
#: pooled from the pixels (FLIP or Cycles' error between the half buffers, the display range
#: of the mean), and measured between AVX-512 and AVX2 code it moved by 2.6e-5 at most,
#: relative, less than the pixels did (4.8e-5): `make test-portability` prints both. The
#: closest decision of the cases sits at 5.2e-4 (cornell_budget), twice the bound.
MARGIN = IMAGE_RTOL

#: env: "cpu,vector_width" (e.g. "haswell,8"): the LLVM target the golden tests compile for
LLVM_TARGET_ENV = "NOISESTOP_TEST_LLVM_TARGET"


def set_llvm_target(spec: str) -> tuple[str, int]:
    """Make Dr.Jit's LLVM backend compile for another CPU ("cpu,vector_width", e.g.
    "haswell,8": AVX2 code on an AVX-512 machine), from now on in this process. Dr.Jit
    exports `jit_llvm_set_target` from its core library but not to Python, so it is called
    through ctypes (its C++ name); returns the target now in force, read back."""
    import drjit as dr

    cpu, _, width = spec.partition(",")
    if not cpu or not width.isdigit() or int(width) & (int(width) - 1):
        raise ValueError(f"{LLVM_TARGET_ENV}: expected 'cpu,vector_width' with a power of two, got {spec!r}")
    dr.eval(dr.llvm.Float(0.0))                                  # the backend is initialised
    lib = ctypes.CDLL(os.path.join(os.path.dirname(dr.__file__), "libdrjit-core.so"))
    set_target = lib._Z19jit_llvm_set_targetPKcS0_j
    set_target.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_uint32]
    set_target(cpu.encode(), None, int(width))    # no feature list: only the cpu's own
    get_cpu, get_width = lib._Z19jit_llvm_target_cpuv, lib._Z21jit_llvm_vector_widthv
    get_cpu.restype, get_width.restype = ctypes.c_char_p, ctypes.c_uint32
    return get_cpu().decode(), int(get_width())


def image_mismatch(image: np.ndarray, golden: np.ndarray) -> tuple[int, float]:
    """(pixels out of bound, largest relative difference) of `image` against `golden`:
    a pixel is in bound when |image - golden| <= IMAGE_RTOL |golden| + IMAGE_ATOL."""
    if image.shape != golden.shape:
        return int(golden.size), float("inf")
    diff = np.abs(image.astype(np.float64) - golden)
    out = diff > IMAGE_RTOL * np.abs(golden) + IMAGE_ATOL
    rel = diff / np.maximum(np.abs(golden), IMAGE_ATOL)
    return int(out.sum()), float(rel.max(initial=0.0))


@dataclass
class DecisionLog:
    """Every quantity a decision of one render compared with a threshold, relative to it:
    score / threshold of each asked block (the criterion's per-block ratio: flip's e / c or
    its dot term over tau, whichever decides; variance's worst pixel over its limit), the
    flat test's display range over its tolerance, and in budget rounds each block's
    priority over the band's cut (the rounds that stopped blocks apart). One value per row
    and block, in decision order, so two runs can be compared value for value."""

    values: list[np.ndarray] = field(default_factory=list)

    @property
    def margin(self) -> float:
        """The smallest |value - 1|: how close the closest call came."""
        vals = np.concatenate(self.values) if self.values else np.zeros(0)
        vals = vals[np.isfinite(vals)]
        return float(np.abs(vals - 1.0).min(initial=np.inf))

    def attach(self, crit: Any, budget_cls: Any) -> Any:
        """Record `crit`'s decisions and the rounds of `budget_cls`; returns an undo."""
        from learning.stoprule import FLAT_TOLERANCE
        from noisefeat.display import display_range
        from renderer.live.budget import BAND

        decide, select = crit.decide, budget_cls.select

        def logged_decide(ids: Any, batch: Any) -> Any:
            out = decide(ids, batch)
            flat = display_range(batch.mean, getattr(crit, "exposure", 0.0)) / FLAT_TOLERANCE
            self.values += [out.ratio, flat]
            return out

        def logged_select(budget: Any, loop: Any, elapsed: float = 0.0) -> list[int]:
            picked = select(budget, loop, elapsed)
            ids = np.flatnonzero(loop.pending())
            priority = budget.priority(loop, ids)          # what the round was chosen by
            if picked and np.isfinite(priority).all():
                self.values.append(priority / (BAND * priority.max()))
            return picked

        crit.decide = logged_decide
        budget_cls.select = logged_select

        def undo() -> None:
            del crit.decide
            budget_cls.select = select
        return undo


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


def render_case(case: str, grow: bool = True, log: DecisionLog | None = None):
    """One golden case rendered by the current loop (`run_adaptive`, grown passes or a
    fixed step): its `RenderResult`, to hold against the recorded stops and image; with
    `log`, every decision's distance from its threshold is recorded there."""
    from renderer.live.adaptive import run_adaptive
    from renderer.live.budget import Budget
    from renderer.criteria import make_criterion
    from renderer.spec import resolve

    _, scene, kw = next(c for c in CASES if c[0] == case)
    # built for the case's grain (its block and tile), as the render builds it
    crit = make_criterion(resolve({k: kw.get(k) for k in ("criterion", "tau", "threshold", "block", "tile",
                                                          "resolution")}))
    undo = log.attach(crit, Budget) if log is not None else None
    try:
        return run_adaptive(load(scene), crit, progress=False, grow=grow,
                            **{k: v for k, v in kw.items() if k not in ("criterion", "threshold", "tau")})
    finally:
        if undo is not None:
            undo()


def record(out: str) -> None:
    """Write the golden file: every case's image, stops and converged flags."""
    arrays = {}
    for name, scene, kw in CASES:
        r = renderer.render(load(scene), progress=False, **kw)
        arrays[f"{name}/image"] = r.image
        arrays[f"{name}/block_spp"] = np.array([b["spp"] for b in r.report["blocks"]], np.int64)
        arrays[f"{name}/converged"] = np.array([b["converged"] for b in r.report["blocks"]], bool)
        print(name, r.report["variant"], arrays[f"{name}/block_spp"].tolist())
    np.savez_compressed(out, **arrays)


def apply_target_from_env() -> str | None:
    """Compile for `LLVM_TARGET_ENV`'s target if it is set and the variant is an LLVM one;
    returns what is in force ("haswell,8"), None when nothing changed."""
    spec = os.environ.get(LLVM_TARGET_ENV)
    if not spec:
        return None
    from learning.data.variant import select_variant

    if not select_variant().startswith("llvm"):
        return None
    cpu, width = set_llvm_target(spec)
    return f"{cpu},{width}"


def log_cases(out: str) -> None:
    """Render every case (grown passes) with a `DecisionLog` on this process's target; save
    each image, stops and logged values for `shift`."""
    print("target", apply_target_from_env() or "native", flush=True)
    arrays = {}
    for name, _, _ in CASES:
        log = DecisionLog()
        r = render_case(name, True, log)
        arrays[f"{name}/image"] = r.image
        arrays[f"{name}/block_spp"] = np.array([b["spp"] for b in r.report["blocks"]], np.int64)
        arrays[f"{name}/values"] = np.concatenate(log.values)
    np.savez_compressed(out, **arrays)


def shift(target: str) -> None:
    """The portability figures: every case rendered natively and for `target`, each in a
    fresh process with its own kernel cache; per case whether the stops agree, the largest
    relative pixel difference (bound IMAGE_RTOL), the largest relative move of a decision's
    quantity and the case's margin (bound MARGIN)."""
    import subprocess
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        runs = {}
        for key, spec in (("native", None), ("target", target)):
            env = {**os.environ, "DRJIT_CACHE_DIR": os.path.join(tmp, f"cache-{key}")}
            env.pop(LLVM_TARGET_ENV, None)
            if spec:
                env[LLVM_TARGET_ENV] = spec
            out = os.path.join(tmp, f"{key}.npz")
            subprocess.run([sys.executable, "-m", "tests.support.passloop_golden", "log", out], env=env, check=True)
            runs[key] = dict(np.load(out))
    a, b = runs["native"], runs["target"]
    print(f"{'case':18s} stops  pixels(rel)  decisions(rel)  margin   (bounds {IMAGE_RTOL:.1e}, {MARGIN:.1e})")
    for name, _, _ in CASES:
        va, vb = a[f"{name}/values"], b[f"{name}/values"]
        same = np.array_equal(a[f"{name}/block_spp"], b[f"{name}/block_spp"])
        ok = np.isfinite(va) & np.isfinite(vb) & (va != 0) if va.shape == vb.shape else np.zeros(0, bool)
        moved = float((np.abs(va[ok] - vb[ok]) / np.abs(va[ok])).max(initial=0.0)) if ok.size else float("nan")
        _, rel = image_mismatch(b[f"{name}/image"], a[f"{name}/image"])
        margin = DecisionLog([vb]).margin
        print(f"{name:18s} {'equal' if same else 'DIFFER'}  {rel:.2e}     {moved:.2e}        {margin:.2e}")


def main(argv: list[str]) -> None:
    """record OUT | log OUT | shift CPU,WIDTH (module docstring)."""
    cmds = {"record": record, "log": log_cases, "shift": shift}
    if len(argv) != 2 or argv[0] not in cmds:
        raise SystemExit("usage: python -m tests.support.passloop_golden record OUT | log OUT | shift CPU,WIDTH")
    cmds[argv[0]](argv[1])


if __name__ == "__main__":
    main(sys.argv[1:])
