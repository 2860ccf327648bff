"""benchmarks.bench_equal_time at a tiny size: the rows it compares, the rules its
verdicts follow and the reference it keeps, whatever the machine's speed (the timing goals
live in BENCHMARKS.md)."""
from __future__ import annotations

import json

import numpy as np
import pytest

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def ran(tmp_path_factory) -> tuple[dict, object]:
    from benchmarks.bench_equal_time import bench_equal_time

    refs = tmp_path_factory.mktemp("refs")
    return bench_equal_time(("cornell_box",), size=64, max_spp=64, ref_spp=128, ref_dir=refs, make_run=False), refs


def test_each_run_is_judged_against_one_reference_and_the_verdicts_follow_the_rows(ran) -> None:
    """The adaptive render, mi.render at max spp and at one and two times the adaptive wall
    time (its own rate), each judged; time to mi.render's quality only when the adaptive
    frame has no more blocks above tau; the result is JSON."""
    from benchmarks.bench_equal_time import md_equal_time

    r, refs = ran
    json.dumps(r)
    (s,) = r["scenes"]
    rows = s["rows"]
    assert set(rows) == {"adaptive", "mi_render_max", "mi_render_1x", "mi_render_2x"}
    assert rows["mi_render_max"]["spp"] == 64 and 0 < rows["adaptive"]["mean_spp"] <= 64
    assert abs(rows["mi_render_2x"]["spp"] - 2 * rows["mi_render_1x"]["spp"]) <= 1
    for x in rows.values():
        assert x["blocks"] == 1 and 0 <= x["above_tau"] <= 1 and 0 <= x["tiles_above_tau"] <= 16
        assert 0 < x["worst"] <= 1 and np.isfinite(x["mean"])
    a, m = rows["adaptive"], rows["mi_render_max"]
    assert 0 <= a["dark_tiles_stopped_above_tau"] <= a["tiles_stopped_above_tau"] <= a["tiles_above_tau"]
    reached = a["above_tau"] <= m["above_tau"]
    assert (s["time_to_mi_quality"] is not None) == reached
    if reached:
        assert s["time_to_mi_quality"] == pytest.approx(a["wall_s"] / m["wall_s"])
    text = md_equal_time(r)
    assert "cornell_box 64x64" in text and ("**met**" in text or "**missed**" in text)
    assert s["reference"].startswith("mi.render 128 spp") and list(refs.glob("cornell_box_64_128.exr"))


def test_the_reference_is_rendered_once_then_read_back(ran) -> None:
    """A second run reads the kept reference (same pixels), rendering no new one."""
    import mitsuba as mi

    from benchmarks.bench_equal_time import reference_for
    from learning.data.exr import read_exr

    _, refs = ran
    path = refs / "cornell_box_64_128.exr"
    ref, source = reference_for("cornell_box", mi.load_dict(mi.cornell_box()), 64, 128, refs)
    assert "cached" in source and np.array_equal(ref, read_exr(path).astype(np.float32))


def test_make_runs_comparison_gives_uniform_its_time_and_twice_it() -> None:
    """`make run`'s settings (a short max spp here): uniform's two runs get the adaptive wall
    time and twice it, and the 2x verdict follows their figures."""
    from benchmarks.bench_equal_time import measure_make_run

    r = measure_make_run(0.02, max_spp=64)
    a, u1, u2 = r["adaptive"], r["uniform_1x"], r["uniform_2x"]
    assert r["settings"]["max_spp"] == 64 and a["blocks"] == u1["blocks"] == u2["blocks"] == 16
    assert u2["mean_spp"] >= u1["mean_spp"] > 0
    assert r["uniform_2x_matches"] == (u2["above_tau"] <= a["above_tau"] and u2["worst"] <= a["worst"])


def test_a_stopped_noisy_tile_is_counted_where_its_window_is() -> None:
    """`judged` maps each tile through its window: a noisy tile the criterion stopped counts,
    the same noise in a tile that ran to max spp does not; near black where the reference is."""
    from benchmarks.bench_equal_time import judged

    rng = np.random.default_rng(0)
    ref = np.full((64, 64, 3), 0.5, np.float32)
    ref[:, 32:] = 5e-4                                           # the right half near black
    img = ref.copy()
    for x, y in ((16, 0), (48, 32), (0, 48)):                    # three noisy tiles
        img[y:y + 16, x:x + 16] += rng.uniform(0, 1.0, (16, 16, 3)).astype(np.float32)
    tiles = [{"window": [x, y, 16, 16], "converged": (x, y) in ((16, 0), (48, 32))}
             for y in range(0, 64, 16) for x in range(0, 64, 16)]
    r = judged(img, ref, 0.15, tiles=tiles)              # a loud tau: FLIP spreads a little noise
    assert r["tiles_above_tau"] == 3
    assert r["tiles_stopped_above_tau"] == 2 and r["dark_tiles_stopped_above_tau"] == 1
