"""Render settings come from what a door was given, the scene plugin, the reference stack,
the scene, then defaults (`renderer.spec.resolve`)."""
from __future__ import annotations

import pytest

from learning import make_synthetic_stack
from renderer.live.adaptive import adaptive_render
from renderer.criteria import UniformCriterion
from renderer.settings import ROWS
from renderer.spec import FIELDS, RenderSpec, reference_settings, resolve


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    # 64x64, grid 4x4, evenly spaced levels 8, 16, 24, 32
    return make_synthetic_stack(tmp_path_factory.mktemp("ref") / "s", size=64, seed=1, spp=[8, 16, 24, 32],
                                thresholds=[16] * 16)


def test_nothing_given_means_scene_resolution_and_documented_defaults():
    spec = resolve({})
    assert spec.resolution is None and spec.sources["resolution"] == "scene"
    assert spec.grid is None and spec.sources["grid"] == "not used"
    for row in ROWS:
        if row.name not in ("resolution", "grid", "criterion"):
            assert getattr(spec, row.name) == row.default and spec.sources[row.name] == "default", row.name
    assert spec.criterion == "flip" and spec.sources["criterion"] == "default"


def test_the_spec_is_a_typed_frozen_dataclass_of_the_rows():
    """RenderSpec is declared in code, one typed field per row in the rows' order (so the
    two cannot drift), frozen, and what `resolve` returns."""
    import dataclasses
    import typing

    assert FIELDS == tuple(r.name for r in ROWS)
    hints = typing.get_type_hints(RenderSpec)
    assert set(hints) == {*FIELDS, "sources"} and typing.Any not in hints.values()
    spec = resolve({"tau": 0.05})
    assert type(spec) is RenderSpec and spec.tau == 0.05
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.tau = 0.1      # type: ignore[misc]


def test_command_line_beats_reference_beats_defaults(stack):
    implied = reference_settings(stack)
    assert implied["grid"] == tuple(stack.grid) and implied["resolution"] == stack.width
    assert implied["max_spp"] == stack.spp[-1] and implied["min_spp"] == stack.spp[0]
    spec = resolve({"step": 7, "grid": None}, source="command line", reference=stack)
    assert spec.step == 7 and spec.sources["step"] == "command line"
    assert spec.grid == tuple(stack.grid) and spec.sources["grid"].startswith("reference")
    assert spec.block is None and spec.sources["block"] == "not used"
    assert spec.max_spp == stack.spp[-1]
    assert "step 7 (command line)" in spec.describe()
    # a block size given beats the reference's grid
    spec = resolve({"block": 16}, reference=stack)
    assert spec.block == 16 and spec.grid is None and spec.sources["block"] == "argument"


def test_uneven_reference_levels_imply_no_step(stack, tmp_path):
    from learning.data.stack_write import write_stack
    st = write_stack(tmp_path / "u", scene="u", spp=[4, 8, 32], levels=[stack.level(k) for k in range(3)],
                     reference=stack.reference(), quick=None, reference_spp=stack.reference_spp,
                     grid=stack.grid)
    assert "step" not in reference_settings(st)
    assert resolve({}, reference=st).sources["step"] == "default"


def test_a_given_bound_wins_over_a_defaulted_one():
    spec = resolve({"max_spp": 8})
    assert spec.min_spp == 8 and "clipped" in spec.sources["min_spp"]
    spec = resolve({"min_spp": 2048})
    assert spec.max_spp == 2048 and "clipped" in spec.sources["max_spp"]
    spec = resolve({"max_spp": 8}, plugin={"min_spp": 32})     # given beats the scene plugin's
    assert spec.min_spp == 8 and "clipped" in spec.sources["min_spp"]
    with pytest.raises(ValueError, match="min_spp .32. is above max_spp .8."):
        resolve({"max_spp": 8, "min_spp": 32})                # both given: no winner, an error
    with pytest.raises(ValueError, match="unknown render setting 'spp'"):
        resolve({"spp": 3})


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
    src = r["settings_source"]
    assert {k: src[k] for k in ("resolution", "grid", "step", "min_spp", "max_spp")} == {
        "resolution": "scene", "grid": "argument", "step": "argument", "min_spp": "argument",
        "max_spp": "argument"}
    assert "block" not in src and src["tau"] == "default"


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
    assert all(r["settings_source"][k].startswith("reference") for k in ("grid", "max_spp", "min_spp", "step"))
