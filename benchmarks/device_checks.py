"""Checks of the device loop on whatever device the variant uses (the GPU run's first part).

CI has no GPU, so what the CPU tests hold (tests/renderer/test_device_loop.py) is checked
here on the GPU, by hand, once per change of the loop:

* the fixture renders (tests/fixtures/passloop_golden.npz, `tests.support.passloop_golden`, recorded with the host loop on
  ``llvm_ad_rgb``) against the device loop, grown passes and fixed step: stops per block
  and the largest pixel difference (on another device the path tracer's float arithmetic
  differs, so differences are reported, not asserted);
* FLIP between half buffers on the device against ``flip-evaluator`` on the fixture
  dataset's stacks (goal: within 1e-3).

    python -m benchmarks.device_checks
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def golden() -> list[str]:
    from tests.support import passloop_golden as g

    gold = np.load(ROOT / "tests" / "fixtures" / "passloop_golden.npz")
    lines = []
    for name, _, _ in g.CASES:
        for grow in (True, False):
            r = g.render_case(name, grow)
            spp = np.array([b["spp"] for b in r.report["blocks"]])
            want = gold[f"{name}/block_spp"]
            lines.append(f"{name} grow={grow}: {r.report['variant']}, stops equal {np.array_equal(spp, want)} "
                         f"({int((spp == want).sum())}/{len(want)}), largest pixel difference "
                         f"{np.abs(r.image - gold[f'{name}/image']).max():.3g}")
    return lines


def flip_on_device() -> list[str]:
    import torch

    from learning.data.dataset_dir import read_stacks
    from learning.inputs.halves import halves_flip_evaluator, iter_stack_halves
    from noisefeat.flip import flip_halves_tensor

    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    worst, n = 0.0, 0
    t_dev = 0.0
    for st in read_stacks(ROOT / "tests" / "fixtures" / "dataset"):
        for _, even, odd in iter_stack_halves(st):
            ref = halves_flip_evaluator(even, odd)
            t0 = time.perf_counter()
            got = flip_halves_tensor(torch.from_numpy(even).to(device), torch.from_numpy(odd).to(device)).cpu().numpy()
            t_dev += time.perf_counter() - t0
            worst = max(worst, float(np.abs(got - ref).max()))
            n += len(ref)
    return [f"FLIP between halves on {device}: {n} blocks, largest difference to flip-evaluator {worst:.2e} "
            f"(goal <= 1e-3), {t_dev:.2f} s"]


def main() -> int:
    from learning.data.variant import select_variant
    from renderer.plugin import register

    print("variant", select_variant())
    register()
    for line in golden() + flip_on_device():
        print(line, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
