"""Render settings come from the command line, the reference stack, the scene, then defaults."""
from __future__ import annotations

import pytest

from learning import make_synthetic_stack
from renderer.adaptive import adaptive_render
from renderer.criteria import UniformCriterion
from renderer.settings import DEFAULTS, describe, reference_settings, resolve_settings


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    # 64x64, grid 4x4, evenly spaced levels 8, 16, 24, 32
    return make_synthetic_stack(tmp_path_factory.mktemp("ref") / "s", size=64, seed=1, spp=[8, 16, 24, 32],
                                thresholds=[16] * 16)


def test_nothing_given_means_scene_resolution_and_documented_defaults():
    values, sources = resolve_settings({})
    assert values["resolution"] is None and sources["resolution"] == "scene"
    assert {k: values[k] for k in DEFAULTS} == DEFAULTS
    assert all(sources[k] == "default" for k in DEFAULTS)


def test_command_line_beats_reference_beats_defaults(stack):
    implied = reference_settings(stack)
    assert implied["grid"] == tuple(stack.grid) and implied["resolution"] == stack.width
    assert implied["max_spp"] == stack.spp[-1] and implied["min_spp"] == stack.spp[0]
    values, sources = resolve_settings({"step": 7, "grid": None}, stack)
    assert values["step"] == 7 and sources["step"] == "command line"
    assert values["grid"] == tuple(stack.grid) and sources["grid"].startswith("reference")
    assert values["max_spp"] == stack.spp[-1]
    assert "step 7 (command line)" in describe(values, sources)


def test_uneven_reference_levels_imply_no_step(stack, tmp_path):
    from learning.data.stack_write import write_stack
    st = write_stack(tmp_path / "u", scene="u", spp=[4, 8, 32], levels=[stack.level(k) for k in range(3)],
                     reference=stack.reference(), quick=None, reference_spp=stack.reference_spp,
                     grid=stack.grid)
    assert "step" not in reference_settings(st)
    _, sources = resolve_settings({}, st)
    assert sources["step"] == "default"


def test_a_given_bound_wins_over_a_defaulted_one():
    values, sources = resolve_settings({"max_spp": 8})
    assert values["min_spp"] == 8 and "clipped" in sources["min_spp"]
    values, sources = resolve_settings({"min_spp": 2048})
    assert values["max_spp"] == 2048 and "clipped" in sources["max_spp"]
    with pytest.raises(ValueError, match="unknown"):
        resolve_settings({"spp": 3})


@pytest.mark.slow
def test_render_takes_an_xml_scenes_own_film_and_reports_sources(tmp_path):
    xml = tmp_path / "fixed.xml"
    xml.write_text("""<scene version="3.0.0">
  <sensor type="perspective"><film type="hdrfilm">
      <integer name="width" value="40"/><integer name="height" value="24"/><rfilter type="box"/>
  </film></sensor>
  <emitter type="constant"/>
</scene>""")
    r = adaptive_render(str(xml), tmp_path / "o", UniformCriterion(), grid=(2, 2), step=4, min_spp=4,
                        max_spp=8, progress=False)
    assert r["resolution"] == [40, 24] and r["block"] == [12, 20]
    assert r["settings_source"] == {"resolution": "scene", "grid": "command line", "step": "command line",
                                    "min_spp": "command line", "max_spp": "command line"}


@pytest.mark.slow
def test_render_follows_its_reference_stack(tmp_path, stack):
    # the synthetic stack is scene 'synthetic'; render a built-in under that reference's settings
    import shutil
    ref = tmp_path / "ref" / "sky"
    shutil.copytree(stack.path, ref)
    meta = (ref / "meta.json").read_text().replace('"scene": "synthetic"', '"scene": "sky"')
    (ref / "meta.json").write_text(meta)
    r = adaptive_render("sky", tmp_path / "o", UniformCriterion(), reference=ref, progress=False)
    assert r["resolution"] == [stack.width, stack.height] and r["grid"] == list(stack.grid)
    assert r["max_spp"] == stack.spp[-1] and r["step"] == stack.spp[0]
    assert all(v.startswith("reference") for v in r["settings_source"].values())
