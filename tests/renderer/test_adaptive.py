"""The adaptive loop on real (tiny) renders: resume identity, degenerate scenes, outputs, farm."""
from __future__ import annotations

import json

import numpy as np
import pytest

from learning import make_synthetic_stack
from learning.models.bundle import load_model, save_model
from learning.models.estimators import DSVM
from learning.data.exr import read_exr
from learning.inputs.table import stack_features
from renderer.live import adaptive
from renderer.live.adaptive import CHECKPOINT, adaptive_render
from renderer.render_many import render_command, render_many
from renderer.live.passloop import schedule
from renderer.live.blocks import BlockRenderer
from renderer.criteria import ModelCriterion, OracleCriterion, UniformCriterion, VarianceCriterion

pytestmark = pytest.mark.slow

TINY = {"resolution": 32, "grid": (4, 4), "step": 4, "min_spp": 4, "max_spp": 24, "progress": False,
        "checkpoint_every": 0.0}    # every pass: the crash tests resume from the pass before the crash
TIMING_KEYS = {"wall_s", "timing", "render_calls"}   # the process's own costs


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    d = tmp_path_factory.mktemp("model")
    st = make_synthetic_stack(d / "train", size=64, seed=3)
    x = stack_features(st)
    est = DSVM(C=10.0).fit(x.reshape(-1, x.shape[-1]), st.labels().reshape(-1))
    return load_model(save_model(est, d / "model", kind="dsvm", input="features"))


def without_timing(report):
    return {k: v for k, v in report.items() if k not in TIMING_KEYS}


class Crash(RuntimeError):
    pass


class CrashOnThirdDecision:
    """Mixin: dies on the third decision, i.e. after at least two passes were checkpointed."""

    def _decide(self, ids, batch, tally):
        self.calls = getattr(self, "calls", 0) + 1       # the test's own count: a criterion keeps none
        if self.calls == 3:
            raise Crash("simulated crash")
        return super()._decide(ids, batch, tally)


class CrashingVariance(CrashOnThirdDecision, VarianceCriterion):
    pass


class CrashingModel(CrashOnThirdDecision, ModelCriterion):
    pass


@pytest.mark.parametrize("kind", ["variance", "model"])
def test_resume_gives_the_uninterrupted_result(tmp_path, monkeypatch, model, kind):
    def make(crash=False):
        if kind == "variance":
            return (CrashingVariance if crash else VarianceCriterion)(0.3)
        return (CrashingModel if crash else ModelCriterion)(model)

    ref = adaptive_render("cornell", tmp_path / "a", make(), **TINY)
    if kind == "variance":
        assert 0 < ref["blocks_converged"] < 16      # some blocks stop early, some do not
    assert ref["passes"] > 2
    with pytest.raises(Crash):
        adaptive_render("cornell", tmp_path / "b", make(crash=True), **TINY)
    assert not (tmp_path / "b" / "report.json").exists()
    with np.load(tmp_path / "b" / CHECKPOINT, allow_pickle=False) as z:
        crashed_at = int(z["pass_index"])           # the passes before the third decision (skipped ones too)
        assert 2 <= crashed_at < ref["passes"] and not bool(z["done"])
    passes = []
    real = BlockRenderer.submit_passes
    monkeypatch.setattr(BlockRenderer, "submit_passes",
                        lambda self, jobs, spp, seed: passes.extend(sorted({p for _, p in jobs})) or
                        real(self, jobs, spp, seed))
    resumed = adaptive_render("cornell", tmp_path / "b", make(), resume=True, **TINY, grow=False)
    assert passes == list(range(crashed_at, ref["passes"]))   # continued, did not start over
    assert without_timing(resumed) == without_timing(ref)
    np.testing.assert_array_equal(read_exr(tmp_path / "b" / "final.exr"), read_exr(tmp_path / "a" / "final.exr"))
    on_disk = json.loads((tmp_path / "b" / "report.json").read_text())
    assert on_disk["counters"] == ref["counters"] and on_disk["blocks"] == ref["blocks"]
    # a finished run resumed again renders nothing more
    passes.clear()
    again = adaptive_render("cornell", tmp_path / "b", make(), resume=True, **TINY, grow=False)
    assert without_timing(again) == without_timing(ref) and passes == []
    # resuming with other settings is refused, not mixed
    with pytest.raises(ValueError, match="other settings.*step"):
        adaptive_render("cornell", tmp_path / "b", make(), resume=True, **{**TINY, "step": 8})


@pytest.mark.parametrize("scene", ["allblack", "sky"])
@pytest.mark.parametrize("kind", ["variance", "model"])
def test_degenerate_scenes_stop_at_min_spp(tmp_path, model, scene, kind):
    crit = VarianceCriterion() if kind == "variance" else ModelCriterion(model)
    r = adaptive_render(scene, tmp_path, crit, **{**TINY, "max_spp": 64})
    assert [b["spp"] for b in r["blocks"]] == [4] * 16
    assert all(b["converged"] for b in r["blocks"])
    assert r["passes"] == 1 and r["saved_vs_uniform"] == pytest.approx(1 - 4 / 64)
    assert r["counters"]["flat_blocks"] == 16


def test_only_active_blocks_are_rendered_and_asked(tmp_path, model, monkeypatch):
    calls = []
    real = BlockRenderer.quick_image

    def counting_quick(self, *a, **k):
        calls.append(1)
        return real(self, *a, **k)

    monkeypatch.setattr(BlockRenderer, "quick_image", counting_quick)
    rendered = []
    real_passes = BlockRenderer.submit_passes

    def counting_passes(self, jobs, spp, seed):
        (pass_index,) = {p for _, p in jobs}             # one pass per launch without grow
        rendered.append(([b for b, _ in jobs], pass_index))
        return real_passes(self, jobs, spp, seed)

    monkeypatch.setattr(BlockRenderer, "submit_passes", counting_passes)
    r = adaptive_render("cornell", tmp_path / "m", ModelCriterion(model), **{**TINY, "min_spp": 8}, grow=False)
    assert len(calls) == 1                                        # quick image: once, model needs it
    per_pass = r["counters"]["blocks_rendered_per_pass"]
    assert per_pass == [len(ids) for ids, _ in rendered]
    assert [p for _, p in rendered] == list(range(len(rendered)))
    assert all(b == sorted(b) for b, _ in rendered)
    # a block stopped at spp s was rendered s / step times, never after
    for blk in r["blocks"]:
        times = sum(blk["id"] in ids for ids, _ in rendered)
        assert times * 4 == blk["spp"]
        verdicts = [v for _, v in blk["history"]]
        assert all(v == -1 for v in verdicts[:-1]) and (verdicts[-1] == 1) == blk["converged"]
    # decisions: every rendered block from 8 spp on (pass 0 is below min_spp)
    assert r["counters"]["decisions"] == sum(per_pass[1:])
    assert r["counters"]["blocks_featured"] + r["counters"]["flat_blocks"] == r["counters"]["decisions"]
    calls.clear()
    adaptive_render("cornell", tmp_path / "v", VarianceCriterion(), **TINY, grow=False)
    assert calls == []                                            # variance: no quick image


@pytest.mark.parametrize("quick", ["direct", "none"])
def test_the_loop_renders_the_quick_image_the_model_was_trained_with(tmp_path, model, monkeypatch, quick):
    kinds = []
    real = BlockRenderer.quick_image

    def recording_quick(self, *a, **k):
        kinds.append(k.get("kind", "albedo"))
        return real(self, *a, **k)

    monkeypatch.setattr(BlockRenderer, "quick_image", recording_quick)
    m = load_model(model.path)
    m.manifest["quick"] = quick
    r = adaptive_render("cornell", tmp_path, ModelCriterion(m), **TINY)
    assert kinds == ([] if quick == "none" else [quick])   # 'none': no quick image at all
    assert r["quick"] == quick


def test_outputs_and_report(tmp_path):
    r = adaptive_render("cornell", tmp_path, UniformCriterion(), **TINY)
    assert r["passes"] == 6 and r["counters"]["blocks_rendered_per_pass"] == [16] * 6
    for name in ("final.exr", "final.png", "spp_map.png", "report.json"):
        assert (tmp_path / name).stat().st_size > 0, name
    img = read_exr(tmp_path / "final.exr")
    assert img.shape == (32, 32, 3) and np.isfinite(img).all() and img.mean() > 0.01
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["saved_vs_uniform"] == 0.0 and rep["variant"] and rep["wall_s"] > 0
    assert [b["spp"] for b in rep["blocks"]] == [24] * 16 and not any(b["converged"] for b in rep["blocks"])
    t = rep["timing"]
    assert t["render_s"] > 0 and abs(sum(t.values()) - rep["wall_s"]) < 1e-6 + 1e-3 * rep["wall_s"]
    assert rep["samples_spent"] == 24 * 32 * 32
    assert rep["blocks"] == r["blocks"] and set(t) == {"setup_s", "render_s", "features_s", "decisions_s",
                                                       "overhead_s"}
    from learning.data.exr import read_png
    png = read_png(tmp_path / "spp_map.png")
    assert png.shape[0] >= 400 and png.std() > 0.05             # a real picture, not a blank canvas


def test_reference_metrics_and_oracle(tmp_path):
    th = [4, 8, 12, 16, 20, 24, None, 4, 8, 12, 16, 20, 24, None, 6, 10]
    make_synthetic_stack(tmp_path / "data" / "cornell", scene="cornell", size=32, spp=(4, 8, 12, 16, 20, 24),
                         thresholds=th)
    r = adaptive_render("cornell", tmp_path / "o", "oracle", reference=tmp_path / "data", **TINY)
    assert [b["spp"] for b in r["blocks"]] == [t or 24 for t in [4, 8, 12, 16, 20, 24, None, 4, 8, 12, 16, 20,
                                                                   24, None, 8, 12]]
    assert r["early_stop_rate"] == 0.0 and r["spp_ratio_vs_oracle"] == pytest.approx(1.0)
    assert [b["true_threshold"] for b in r["blocks"]] == th
    u = adaptive_render("cornell", tmp_path / "u", OracleCriterion([4] * 16), reference=tmp_path / "data", **TINY)
    assert u["early_stop_rate"] == pytest.approx(14 / 16)         # all but the two T=4 blocks
    assert u["spp_ratio_vs_oracle"] < 1.0
    with pytest.raises(ValueError, match="oracle criterion needs true thresholds"):
        render_command("cornell", tmp_path / "x", {"criterion": "oracle"})
    # the finished image against the reference, as a person flipping between them would see it:
    # this synthetic 'reference' is another picture altogether, so every block differs visibly
    check = r["final_vs_reference"]
    assert check["tau"] == 0.02 and len(check["errors"]) == 16 and check["visible_noise_blocks"] == 16
    assert check["visible_noise_stopped_blocks"] == sum(b["converged"] for b in r["blocks"]) > 0
    assert all(0 < e <= 1 for e in check["errors"]) and (tmp_path / "o" / "compare.png").stat().st_size > 1000


def test_a_finished_image_equal_to_its_reference_shows_no_noise(tmp_path):
    from learning import write_stack
    grey = np.full((32, 32, 3), 0.5, np.float32)            # what the 'sky' scene renders, exactly
    write_stack(tmp_path / "data" / "sky", scene="sky", levels=[grey] * 2, spp=[4, 8], reference=grey,
                quick=None, reference_spp=64, thresholds=[4] * 16)
    r = adaptive_render("sky", tmp_path / "o", UniformCriterion(), reference=tmp_path / "data", **TINY)
    assert r["final_vs_reference"]["visible_noise_blocks"] == 0 and max(r["final_vs_reference"]["errors"]) == 0


def test_render_many_on_a_local_pool(tmp_path):
    summary = render_many(["allblack", "sky"], tmp_path, criterion=VarianceCriterion(), workers=1,
                          **{**TINY, "max_spp": 16})
    assert summary["failed"] == {}
    assert set(summary["scenes"]) == {"allblack", "sky"}
    for name in ("allblack", "sky"):
        assert json.loads((tmp_path / name / "report.json").read_text())["scene"] == name
    assert summary["scenes"]["sky"]["blocks"][0]["spp"] == 4


def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="min_spp"):
        adaptive_render("cornell", tmp_path, UniformCriterion(), **{**TINY, "min_spp": 99})
    with pytest.raises(ValueError, match="step must be a whole number in"):
        adaptive_render("cornell", tmp_path, UniformCriterion(), **{**TINY, "step": 0})
    with pytest.raises(ValueError, match="criterion must be one of"):
        adaptive_render("cornell", tmp_path, "bogus", **TINY)
    assert schedule(16, 40).tolist() == [16, 32, 40]


def test_time_limit_stops_cleanly_and_resume_finishes_the_same_image(tmp_path):
    ref = adaptive_render("cornell", tmp_path / "a", VarianceCriterion(0.3), **TINY)
    assert ref["passes"] > 2 and "time_limit" not in ref
    cut = adaptive_render("cornell", tmp_path / "b", VarianceCriterion(0.3), time_limit=1e-6, **TINY)
    assert cut["time_limit"] == {"seconds": 1e-6, "reached": True} and cut["passes"] == 1
    assert (tmp_path / "b" / "final.exr").exists() and (tmp_path / "b" / "report.json").exists()
    with np.load(tmp_path / "b" / CHECKPOINT, allow_pickle=False) as z:
        assert int(z["pass_index"]) == 1 and not bool(z["done"])
    resumed = adaptive_render("cornell", tmp_path / "b", VarianceCriterion(0.3), resume=True, **TINY)
    assert without_timing(resumed) == without_timing(ref)
    np.testing.assert_array_equal(read_exr(tmp_path / "b" / "final.exr"), read_exr(tmp_path / "a" / "final.exr"))
    roomy = adaptive_render("cornell", tmp_path / "c", VarianceCriterion(0.3), time_limit=1e6, **TINY)
    assert roomy["time_limit"]["reached"] is False and roomy["passes"] == ref["passes"]
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="time_limit"):
            adaptive_render("cornell", tmp_path / "d", VarianceCriterion(0.3), time_limit=bad, **TINY)


def test_final_exr_carries_spp_and_the_converged_mask(tmp_path):
    from learning.data.exr import read_exr_channels
    rep = adaptive_render("cornell", tmp_path / "a", VarianceCriterion(0.3), **TINY)
    ch = read_exr_channels(tmp_path / "a" / "final.exr")
    assert {"R", "G", "B", "spp", "converged"} <= set(ch)
    gh, gw = rep["grid"]
    h, w = ch["spp"].shape
    for b, block in enumerate(rep["blocks"]):
        r, c = divmod(b, gw)
        tile = (slice(r * h // gh, (r + 1) * h // gh), slice(c * w // gw, (c + 1) * w // gw))
        assert (ch["spp"][tile] == block["spp"]).all()
        assert (ch["converged"][tile] == float(block["converged"])).all()
    assert 0 < ch["converged"].mean() < 1                  # some blocks stopped, some did not
    np.testing.assert_array_equal(read_exr(tmp_path / "a" / "final.exr"),
                                  np.stack([ch[c] for c in "RGB"], axis=-1))
