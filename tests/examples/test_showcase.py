"""`make run`'s pieces (examples.showcase): the dots each side holds against the reference,
the summary's dots clause, and equal_time.png's 1:1 row."""
from __future__ import annotations

import io

import numpy as np
import pytest
from examples.showcase import block_outliers_vs, darkest_stopped, dots_summary, equal_time_png


def report(stopped: list[bool], spp: list[int], tau: float = 0.02, size: int = 32) -> dict:
    """A 2x2-block report of a 64x64 frame, as adaptive_render writes it (the fields read)."""
    blocks = [{"id": i, "window": [(i % 2) * size, (i // 2) * size, size, size], "spp": s, "converged": c}
              for i, (c, s) in enumerate(zip(stopped, spp))]
    return {"blocks": blocks, "tau": tau, "exposure": 0.0, "mean_spp": float(np.mean(spp)), "wall_s": 1.0,
            "criterion": {"name": "flip"}}


def test_outliers_are_counted_per_block_window():
    ref = np.full((64, 64, 3), 0.2)
    img = ref.copy()
    img[1, 1] = 0.9                 # block 0: one pixel far off
    img[40:43, 40] = 0.0            # block 3: three pixels
    img[5, 40] = 0.2005             # block 1: a pixel off by less than the dot level
    a = report([True] * 4, [64] * 4)
    assert block_outliers_vs(img, ref, a, 0.02).tolist() == [1, 0, 0, 3]
    assert block_outliers_vs(img, ref, a, 10.0).tolist() == [0, 0, 0, 0]      # level 25: nothing is over


def test_the_summary_says_where_adaptive_holds_more_dots_than_uniform():
    a = report([True, True, False, True], [32, 64, 256, 32])
    errors = {"outliers_adaptive": np.array([3, 0, 9, 20]), "outliers_uniform": np.array([1, 0, 2, 0])}
    line = dots_summary(a, errors)
    assert "32 adaptive, 3 uniform" in line
    assert "worst stopped block 20 adaptive, 0 uniform" in line     # block 2 ran on: not a stopped block
    assert line.endswith("blocks with more adaptive than uniform: 3")
    none = dots_summary(report([False] * 4, [256] * 4), errors)
    assert "no block stopped" in none


def test_the_darkest_stopped_block_is_picked_from_the_image():
    img = np.full((64, 64, 3), 0.5)
    img[32:, :32] = 0.01            # block 2 is darkest
    img[:32, :32] = 0.0             # block 0 darker still, but it did not stop
    assert darkest_stopped(report([False, True, True, True], [256, 32, 32, 32]), img)["id"] == 2
    assert darkest_stopped(report([False] * 4, [256] * 4), img) is None


def test_equal_time_png_shows_the_darkest_stopped_block_pixel_for_pixel():
    """The bottom row places each side's crop with figimage: the PNG holds its exact pixels."""
    from matplotlib.image import imread

    rng = np.random.default_rng(0)
    adaptive = rng.integers(0, 256, (64, 64, 3), dtype=np.uint8)
    uniform = rng.integers(0, 256, (64, 64, 3), dtype=np.uint8)
    adaptive[32:, :32] //= 8                                        # block 2: the darkest stopped one
    a, u = report([False, True, True, True], [256, 32, 32, 32]), report([False] * 4, [64] * 4)
    errors = {"adaptive": np.zeros(4), "uniform": np.zeros(4),
              "outliers_adaptive": np.array([0, 0, 7, 0]), "outliers_uniform": np.zeros(4, int)}
    png = imread(io.BytesIO(equal_time_png(adaptive, uniform, a, u, None, errors)))
    got = (png[..., :3] * 255).round().astype(np.uint8)
    height = got.shape[0]
    for col, side in enumerate((adaptive, uniform)):
        x0 = col * 500 + 20                                     # 500-px columns, 20-px margins
        crop = got[height - 20 - 32:height - 20, x0:x0 + 32]
        np.testing.assert_array_equal(crop, side[32:, :32])


def test_equal_time_png_without_stopped_blocks_has_no_bottom_row():
    from matplotlib.image import imread

    img = np.zeros((64, 64, 3), np.uint8)
    none = imread(io.BytesIO(equal_time_png(img, img, report([False] * 4, [256] * 4), report([False] * 4, [64] * 4))))
    some = imread(io.BytesIO(equal_time_png(img, img, report([True] * 4, [32] * 4), report([False] * 4, [64] * 4))))
    assert some.shape[0] - none.shape[0] == 3 * 32 + 2 * 30        # the band of the 1:1 and 3x crops


def test_the_report_counts_dots_in_stopped_blocks_only():
    """`final_vs_reference` (render --reference, the benchmarks): per block the pixels over
    0.05 at tau 0.02, the most in a stopped block, and the stopped blocks over 16."""
    from renderer.live.report import final_vs_reference

    ref = np.zeros((128, 128, 3))
    img = ref.copy()
    img[:64:4, :64:4] = 0.01                 # block 0: 256 dots of display 0.1
    img[:64:4, 64:128:8] = 0.01              # block 1: 128 dots
    img[64:128:16, 0:64:16] = 0.01           # block 2: 16 dots (allowed)
    f = final_vs_reference(img, ref, (2, 2), 0.02, stopped=[False, True, True, True])
    assert f["dots"] == [256, 128, 16, 0] and f["dot_level"] == pytest.approx(0.05)
    assert f["max_stopped_dots"] == 128 and f["dotted_stopped_blocks"] == 1
    assert "max_stopped_dots" not in final_vs_reference(img, ref, (2, 2), 0.02)


def test_the_summary_leads_with_blocks_above_tau_and_the_worst_block():
    """What a user judges first (blocks above tau, the worst block, each side), then
    samples and time, then the mean error."""
    from examples.showcase import summary_line

    a = {**report([True, True, False, True], [32, 64, 256, 32]), "scene": "s", "saved_vs_uniform": 0.5,
         "max_spp": 256, "blocks_converged": 3, "timing": {"setup_s": 0.1, "render_s": 0.9}}
    u = {**report([False] * 4, [128] * 4), "timing": {"setup_s": 0.1, "render_s": 0.9}}
    errors = {"adaptive": np.array([0.01, 0.03, 0.025, 0.0]), "uniform": np.array([0.021, 0.02, 0.04, 0.03]),
              "outliers_adaptive": np.zeros(4, int), "outliers_uniform": np.zeros(4, int)}
    line = summary_line(a, u, errors)
    above = line.index("blocks above tau 2 adaptive (1 of them at max spp), 3 uniform, of 4")
    worst = line.index("worst block 0.0300 adaptive, 0.0400 uniform")
    samples = line.index("adaptive used 50% of uniform's samples")
    mean = line.index("mean block error 0.0163 adaptive, 0.0278 uniform")
    assert above < worst < samples < mean
    assert summary_line(a, u).startswith("s: adaptive used 50%")           # no reference: cost alone


def test_make_reference_writes_the_stack_builders_mean_in_half_floats(tmp_path, monkeypatch):
    """`make_reference` renders as a stack's reference is rendered (`render_mean`, its own
    seed) and writes it where `shipped_reference` reads it: the same image to half-float
    rounding, finite and lit."""
    from learning.data.variant import select_variant
    from examples import showcase
    from renderer.live.blocks import BlockRenderer
    from renderer.scenes.catalog import load_scene
    from renderer.dataset.stackbuild import BuildSettings, render_mean

    select_variant()
    monkeypatch.setattr(showcase, "REFERENCES", tmp_path)
    monkeypatch.setattr(showcase, "REFERENCE_SPP", 8)
    path = showcase.make_reference("cornell", resolution=32)
    assert path == tmp_path / "cornell.exr"
    got = showcase.shipped_reference("cornell")
    with BlockRenderer(load_scene("cornell", 32), grid=(4, 4)) as br:
        want = render_mean(br, 8, showcase.REFERENCE_SEED, 0, BuildSettings().max_lanes)
    assert got.shape == (32, 32, 3) and np.isfinite(got).all() and got.mean() > 0.01
    np.testing.assert_allclose(got, want, rtol=1e-3, atol=1e-4)
