"""benchmarks.bench_realscenes: the verdict rules (ties within the seeds' spread), the curve
look-ups, and one tiny scene through every row, whatever the machine's speed (the figures
live in BENCHMARKS.md)."""
from __future__ import annotations

import json

import pytest

from benchmarks.bench_realscenes import at_time, compare, time_to_match

CURVE = [{"spp": 64 * (k + 1), "t": 1.0 * (k + 1), "above_tau": max(0, 4 - k), "worst": 0.05 - 0.005 * k}
         for k in range(8)]


def test_a_frame_within_the_seeds_spread_is_a_tie_not_a_win() -> None:
    seeds = [{"above_tau": 2, "worst": 0.030}, {"above_tau": 3, "worst": 0.034}]
    assert compare({"above_tau": 3, "worst": 0.032}, seeds) == "tie"
    assert compare({"above_tau": 2, "worst": 0.031}, seeds) == "tie"
    assert compare({"above_tau": 1, "worst": 0.033}, seeds) == "win"            # fewer than either seed
    assert compare({"above_tau": 2, "worst": 0.029}, seeds) == "win"            # as few, worst under both
    assert compare({"above_tau": 4, "worst": 0.020}, seeds) == "loss"           # more than either seed
    assert compare({"above_tau": 2, "worst": 0.0347}, seeds) == "loss"          # over 1.02x the larger worst
    assert compare({"above_tau": 2, "worst": 0.0346}, seeds) == "tie"


def test_the_curve_is_read_at_a_time_and_searched_for_a_quality() -> None:
    assert at_time(CURVE, 3.5)["spp"] == 192
    assert at_time(CURVE, 0.5)["spp"] == 64                 # before the first point: the first
    assert at_time(CURVE, 100.0)["spp"] == 512
    assert time_to_match(CURVE, 1, 0.04) == (4.0, True)     # 1 above tau, worst 0.035 <= 0.04
    assert time_to_match(CURVE, 0, 0.001) == (8.0, False)   # never: the curve's end, not reached


@pytest.mark.slow
def test_one_tiny_scene_goes_through_every_row(tmp_path, monkeypatch) -> None:
    """A 64x64 scene file standing in for the suite: the default render, two seeds' curves,
    the time limit and the markdown, all JSON; the reference is kept."""
    import benchmarks.realscenes as suite
    from benchmarks.bench_realscenes import bench_realscenes, md_realscenes

    xml = tmp_path / "tiny" / "scene.xml"
    xml.parent.mkdir()
    xml.write_text(
        '<scene version="3.0.0"><integrator type="path"><integer name="max_depth" value="4"/></integrator>'
        '<sensor type="perspective"><float name="fov" value="40"/><transform name="to_world">'
        '<lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>'
        '<film type="hdrfilm"><integer name="width" value="64"/><integer name="height" value="64"/></film>'
        '</sensor><emitter type="constant"><rgb name="radiance" value="0.8"/></emitter>'
        '<shape type="sphere"><bsdf type="diffuse"/></shape>'
        '<shape type="rectangle"><transform name="to_world"><translate z="-1.5"/><scale value="3"/></transform>'
        '<bsdf type="roughconductor"/></shape></scene>')
    monkeypatch.setattr(suite, "SCENES", {"tiny": suite.SCENES[next(iter(suite.SCENES))]})
    monkeypatch.setattr(suite, "scene_path", lambda name: xml)
    refs = tmp_path / "refs"
    r = bench_realscenes(("tiny",), size=64, max_spp=128, ref_spp=256, ref_dir=refs)
    json.dumps(r)
    (s,) = r["scenes"]
    wall = s["adaptive"]["wall_s"]
    for curve in s["curves"].values():       # to max spp, then on while short of our wall time
        spp, t = [p["spp"] for p in curve], [p["t"] for p in curve]
        assert spp == list(range(64, 64 * len(spp) + 1, 64)) and len(spp) >= 2
        assert all(0 < a < b for a, b in zip(t, t[1:]))
        assert len(spp) == 2 or (t[-2] < wall <= t[-1])
    assert 0 < s["adaptive"]["mean_spp"] <= 128 and s["adaptive"]["blocks"] == 1
    assert s["equal_time_verdict"] in ("win", "tie", "loss") and s["time_limit_verdict"] in ("win", "tie", "loss")
    assert s["time_limit"]["T"] == s["curves"]["1"][1]["t"]      # T: the curve's time at min(1024, max spp)
    assert all(m["spp"] == 128 for m in s["max_spp_mi"].values())
    for x in s["speedup"].values():
        assert x["ratio"] == pytest.approx(x["t"] / s["adaptive"]["wall_s"])
    assert list(refs.glob("realscene_tiny_64_256.exr"))
    text = md_realscenes(r)
    assert "| tiny |" in text and "Equal wall time:" in text and "the default render" in text
    assert "ours with `--criterion estimate`" in md_realscenes({**r, "criterion": "estimate"})
    from benchmarks.charts import realscenes

    png = realscenes(r["scenes"], tmp_path / "curves.png", r["tau"])
    assert open(png, "rb").read(8) == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="unknown suite scene"):
        bench_realscenes(("nope",), size=64, max_spp=64, ref_spp=64, ref_dir=refs)
