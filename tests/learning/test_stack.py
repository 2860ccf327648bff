"""Dataset format v1: EXR/PNG I/O, Stack, write/read, resumable writer, synthetic stacks."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from learning.data.dataset_dir import list_stacks
from learning.data.exr import read_exr, read_png, write_exr, write_png
from learning.data.stack import read_stack
from learning.data.stack_format import MID_GREY_LINEAR
from learning.data.stack_validate import validate_meta
from learning.data.stack_write import update_labels
from learning.data.stack_write import StackWriter, make_plan, write_stack
from learning.data.synthetic import make_synthetic_stack, synthetic_images

RNG = np.random.default_rng(1)


def _img(h=32, w=32, seed=0):
    return np.random.default_rng(seed).random((h, w, 3)).astype(np.float32)


# ----------------------------------------------------------------------------- EXR / PNG

def test_exr_float_roundtrip_is_exact_and_keeps_nonfinite(tmp_path):
    img = _img(8, 12)
    img[0, 0, 0] = np.nan
    img[1, 1, 1] = np.inf
    write_exr(tmp_path / "a.exr", img)
    back = read_exr(tmp_path / "a.exr")
    assert back.dtype == np.float32 and back.shape == (8, 12, 3)
    np.testing.assert_array_equal(back, img)


def test_exr_half_roundtrip_is_close(tmp_path):
    img = _img(8, 8) * 10
    write_exr(tmp_path / "h.exr", img, half=True)
    back = read_exr(tmp_path / "h.exr")
    assert not np.array_equal(back, img)
    np.testing.assert_allclose(back, img, rtol=1e-3)


def test_exr_write_is_atomic_and_leaves_no_temp_files(tmp_path):
    write_exr(tmp_path / "x.exr", _img())
    write_exr(tmp_path / "x.exr", _img(seed=3))  # overwrite
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.exr"]
    np.testing.assert_array_equal(read_exr(tmp_path / "x.exr"), _img(seed=3))


def test_exr_truncated_file_gives_value_error_naming_it(tmp_path):
    p = tmp_path / "t.exr"
    write_exr(p, _img(64, 64))
    data = p.read_bytes()
    for frac in (0.5, 0.95, 0.01):
        p.write_bytes(data[: int(len(data) * frac)])
        with pytest.raises(ValueError, match="t.exr"):
            read_exr(p)


def test_exr_bad_inputs(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.exr"):
        read_exr(tmp_path / "nope.exr")
    (tmp_path / "junk.exr").write_bytes(b"this is not an exr file at all")
    with pytest.raises(ValueError, match="junk.exr"):
        read_exr(tmp_path / "junk.exr")
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        write_exr(tmp_path / "b.exr", np.zeros((4, 4), np.float32))
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        write_exr(tmp_path / "b.exr", np.zeros((0, 4, 3), np.float32))
    assert not (tmp_path / "b.exr").exists()


def test_png_roundtrip_and_errors(tmp_path):
    u8 = RNG.integers(0, 256, (10, 7, 3), dtype=np.uint8)
    write_png(tmp_path / "p.png", u8)
    back = read_png(tmp_path / "p.png")
    assert back.dtype == np.float32 and back.shape == (10, 7, 3)
    np.testing.assert_array_equal(np.round(back * 255).astype(np.uint8), u8)
    with pytest.raises(ValueError, match="uint8"):
        write_png(tmp_path / "q.png", u8.astype(np.float32))
    data = (tmp_path / "p.png").read_bytes()
    (tmp_path / "t.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="t.png"):
        read_png(tmp_path / "t.png")


def test_read_exr_drops_alpha_and_expands_grey(tmp_path):
    pytest.importorskip("mitsuba")
    from learning.data.variant import select_variant

    select_variant()
    import mitsuba as mi

    rgba = _img(4, 5, seed=2)
    rgba = np.concatenate([rgba, np.full((4, 5, 1), 0.5, np.float32)], axis=2)
    mi.Bitmap(rgba, pixel_format=mi.Bitmap.PixelFormat.RGBA).write(str(tmp_path / "a.exr"))
    np.testing.assert_array_equal(read_exr(tmp_path / "a.exr"), rgba[..., :3])
    grey = rgba[..., 0].copy()
    mi.Bitmap(grey).write(str(tmp_path / "y.exr"))
    np.testing.assert_array_equal(read_exr(tmp_path / "y.exr"), np.repeat(grey[..., None], 3, 2))


def test_exr_io_keeps_a_variant_chosen_by_someone_else(tmp_path):
    code = ("import mitsuba as mi, numpy as np; mi.set_variant('scalar_spectral');"
            "from learning.data.exr import write_exr, read_exr;"
            f"write_exr({str(tmp_path / 'v.exr')!r}, np.ones((2, 2, 3), np.float32));"
            f"assert read_exr({str(tmp_path / 'v.exr')!r}).sum() == 12;"
            "print(mi.variant())")
    root = Path(__file__).resolve().parents[2]
    out = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True,
                         text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(root)})
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "scalar_spectral"


# ----------------------------------------------------------------------------- write/read

def _write_small(path: Path, thresholds=None, quick=True, labeler=None):
    spp = [2, 4, 8]
    levels = {s: _img(seed=s) for s in spp}
    return write_stack(path, scene="small", levels=levels, reference=_img(seed=99),
                       quick=_img(seed=7) if quick else None, reference_spp=64,
                       quick_description="albedo aov, 16 spp", renderer="test",
                       thresholds=thresholds, labeler=labeler, note="hello")


def test_write_read_roundtrip(tmp_path):
    th = [4] * 15 + [None]
    st = _write_small(tmp_path / "s", thresholds=th, labeler={"name": "flip", "tau": 0.02})
    back = read_stack(tmp_path / "s")
    assert back == st
    assert back.spp == [2, 4, 8] and back.reference_spp == 64
    assert back.grid == (4, 4) and back.block == (8, 8) and back.n_blocks == 16
    assert back.extras == {"note": "hello"}
    assert back.thresholds == th
    np.testing.assert_array_equal(back.level(1), _img(seed=4))
    np.testing.assert_array_equal(back.level(-1), _img(seed=8))
    np.testing.assert_array_equal(back.reference(), _img(seed=99))
    np.testing.assert_array_equal(back.quick(), _img(seed=7))
    assert back.levels().shape == (3, 32, 32, 3)
    blocks = back.blocks(2)
    assert blocks.shape == (16, 8, 8, 3)
    np.testing.assert_array_equal(blocks[5], _img(seed=8)[8:16, 8:16])
    meta = json.loads((tmp_path / "s" / "meta.json").read_text())
    assert meta["format"] == "noisestop-stack" and meta["version"] == 1
    assert meta["block"] == [8, 8] and meta["thresholds"][-1] is None
    assert sorted(p.name for p in (tmp_path / "s" / "levels").iterdir()) == [
        "000002.exr", "000004.exr", "000008.exr"]
    assert not (tmp_path / "s" / "meta.partial.json").exists()
    assert read_stack(tmp_path / "s" / "meta.json") == st  # the file works too


def test_labels_follow_rule_4(tmp_path):
    th = [2, 4, 8, None, 3, 100] + [8] * 10
    st = _write_small(tmp_path / "s", thresholds=th)
    lab = st.labels()
    assert lab.dtype == np.int8 and lab.shape == (3, 16)
    np.testing.assert_array_equal(lab[:, 0], [1, 1, 1])
    np.testing.assert_array_equal(lab[:, 1], [-1, 1, 1])
    np.testing.assert_array_equal(lab[:, 2], [-1, -1, 1])
    np.testing.assert_array_equal(lab[:, 3], [-1, -1, -1])   # censored
    np.testing.assert_array_equal(lab[:, 4], [-1, 1, 1])     # 3 spp: between levels
    np.testing.assert_array_equal(lab[:, 5], [-1, -1, -1])   # beyond the last level
    unlabelled = _write_small(tmp_path / "u")
    with pytest.raises(ValueError, match="no thresholds"):
        unlabelled.labels()


def test_update_labels_rewrites_meta(tmp_path):
    st = _write_small(tmp_path / "s")
    new = update_labels(st, [8] * 16, {"name": "flip", "tau": 0.05})
    again = read_stack(tmp_path / "s")
    assert again.thresholds == [8] * 16 and again.labeler["tau"] == 0.05 and new == again
    with pytest.raises(ValueError, match="16 blocks"):
        update_labels(st, [8] * 3, None)


def test_stack_without_quick(tmp_path):
    st = _write_small(tmp_path / "s", quick=False)
    assert not (tmp_path / "s" / "quick.exr").exists()
    assert st.quick_description == "none" and not st.has_quick
    q = read_stack(tmp_path / "s").quick()
    assert q.shape == (32, 32, 3) and np.all(q == np.float32(MID_GREY_LINEAR))


def test_extra_direct_quick_image_keeps_the_stack_complete(tmp_path):
    st = _write_small(tmp_path / "s", thresholds=[4] * 16)
    with pytest.raises(FileNotFoundError, match="dataset build"):
        st.quick("direct")
    w = StackWriter(tmp_path / "s", {k: v for k, v in json.loads((tmp_path / "s" / "meta.json").read_text()).items()
                                    if k not in ("labeler", "thresholds")})
    w.write_extra_quick("direct", _img(seed=5))
    assert w.is_complete and read_stack(tmp_path / "s") == st
    np.testing.assert_array_equal(st.quick("direct"), _img(seed=5))
    np.testing.assert_array_equal(st.quick(), st.quick(None))
    with pytest.raises(ValueError, match="kind"):
        w.write_extra_quick("normals", _img())
    with pytest.raises(ValueError, match="kind"):
        st.quick("normals")
    with pytest.raises(ValueError):                 # wrong size: refused like any image
        w.write_extra_quick("direct", _img(h=8))


def test_level_with_wrong_shape_is_refused_on_read(tmp_path):
    st = _write_small(tmp_path / "s")
    write_exr(st.level_path(0), _img(16, 16))
    with pytest.raises(ValueError, match="000002.exr.*meta.json says 32x32"):
        st.level(0)


def _meta_of(tmp_path):
    _write_small(tmp_path / "s")
    return tmp_path / "s" / "meta.json", json.loads((tmp_path / "s" / "meta.json").read_text())


@pytest.mark.parametrize("edit, message", [
    (lambda m: m.update(format="other"), "format is 'other'"),
    (lambda m: m.update(version=2), "only version 1"),
    (lambda m: m.update(version=True), "only version 1"),
    (lambda m: [m.pop("spp"), m.pop("renderer")], "missing required keys: spp, renderer"),
    (lambda m: m.update(width="32"), "width must be a positive integer"),
    (lambda m: m.update(grid=[4]), "grid must be two positive integers"),
    (lambda m: m.update(spp=[2, 8, 4]), "not strictly increasing"),
    (lambda m: m.update(spp=[2, 2.5, 8]), "positive integers only"),
    (lambda m: m.update(block=[4, 4]), "block size"),
    (lambda m: m.update(reference_spp=4), "below the last level"),
    (lambda m: m.update(thresholds=[2] * 5), "thresholds has 5 entries"),
    (lambda m: m.update(thresholds=[2.5] * 16), "block 0: 2.5"),
    (lambda m: m.update(scene="../x"), "path separators"),
])
def test_read_stack_rejects_bad_meta(tmp_path, edit, message):
    path, meta = _meta_of(tmp_path)
    edit(meta)
    path.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="meta.json") as exc:
        read_stack(path.parent)
    assert message in str(exc.value)


def test_validate_meta_reports_every_problem():
    errs = validate_meta({"format": "x", "version": 3, "width": -1, "spp": [3, 1]})
    text = "\n".join(errs)
    for part in ("missing required keys", "format is 'x'", "only version 1",
                 "width must be", "not strictly increasing"):
        assert part in text
    assert validate_meta([1, 2]) == ["meta must be a JSON object, got list"]


def test_read_stack_errors_for_missing_or_broken_meta(tmp_path):
    with pytest.raises(FileNotFoundError, match="not a noisestop stack"):
        read_stack(tmp_path)
    (tmp_path / "meta.partial.json").write_text("{}")
    with pytest.raises(FileNotFoundError, match="incomplete build"):
        read_stack(tmp_path)
    (tmp_path / "meta.json").write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        read_stack(tmp_path)


# ----------------------------------------------------------------------------- the writer

def _plan(**kw):
    base = dict(scene="w", width=32, height=32, spp=[2, 4, 8], reference_spp=64,
                quick="albedo", renderer="test")
    base.update(kw)
    return make_plan(**base)


def test_writer_resumes_an_interrupted_build(tmp_path):
    d = tmp_path / "w"
    w = StackWriter(d, _plan())
    assert (d / "meta.partial.json").is_file() and not (d / "meta.json").exists()
    w.write_level(2, _img(seed=2))
    w.write_reference(_img(seed=99))
    with pytest.raises(ValueError, match="missing 3 file"):
        w.finish()
    with pytest.raises(FileNotFoundError, match="incomplete build"):
        read_stack(d)
    del w  # "crash"; a rerun with the same plan resumes
    w2 = StackWriter(d, _plan())
    assert w2.has_level(2) and not w2.has_level(4) and w2.has_reference()
    assert w2.missing_levels() == [4, 8] and not w2.has_quick()
    w2.write_level(4, _img(seed=4))
    w2.write_level(8, _img(seed=8))
    w2.write_quick(_img(seed=7))
    st = w2.finish([2] * 16, {"name": "test"})
    assert not (d / "meta.partial.json").exists()
    assert read_stack(d) == st and st.labels().min() == 1
    np.testing.assert_array_equal(st.level(0), _img(seed=2))


def test_writer_refuses_a_different_plan_and_foreign_files(tmp_path):
    d = tmp_path / "w"
    StackWriter(d, _plan())
    with pytest.raises(ValueError, match="different plan.*spp"):
        StackWriter(d, _plan(spp=[2, 4, 16]))
    other = tmp_path / "o"
    write_exr(other / "levels" / "000002.exr", _img())
    with pytest.raises(ValueError, match="no meta.json or meta.partial.json"):
        StackWriter(other, _plan())


def test_writer_checks_its_inputs(tmp_path):
    w = StackWriter(tmp_path / "w", _plan())
    with pytest.raises(ValueError, match="spp 3 is not a level"):
        w.write_level(3, _img())
    with pytest.raises(ValueError, match="shape"):
        w.write_level(2, _img(16, 16))
    with pytest.raises(ValueError, match="labeler/thresholds"):
        StackWriter(tmp_path / "x", {**_plan(), "thresholds": None})
    with pytest.raises(ValueError, match="cannot be cut"):
        _plan(width=30)
    nq = StackWriter(tmp_path / "nq", _plan(quick="none"))
    assert nq.has_quick()
    with pytest.raises(ValueError, match="quick = 'none'"):
        nq.write_quick(_img())


def test_writer_rewrites_a_truncated_level_and_reopens_complete_stacks(tmp_path):
    d = tmp_path / "w"
    st = _write_small(d)
    data = st.level_path(1).read_bytes()
    st.level_path(1).write_bytes(data[:100])
    plan = {k: v for k, v in st.meta().items() if k not in ("labeler", "thresholds")}
    w = StackWriter(d, plan)
    assert w.is_complete
    assert not w.has_level(4)                  # verified read fails -> missing
    assert w.has_level(4, verify=False)
    w.write_level(4, _img(seed=4))             # writing un-completes the stack
    assert not (d / "meta.json").exists() and (d / "meta.partial.json").exists()
    st2 = w.finish()
    np.testing.assert_array_equal(st2.level(1), _img(seed=4))


def test_list_stacks(tmp_path):
    _write_small(tmp_path / "a" / "s1")
    _write_small(tmp_path / "b")
    StackWriter(tmp_path / "c", _plan())
    (tmp_path / "empty").mkdir()
    assert list_stacks(tmp_path) == [tmp_path / "a" / "s1", tmp_path / "b"]
    assert list_stacks(tmp_path, include_incomplete=True) == [
        tmp_path / "a" / "s1", tmp_path / "b", tmp_path / "c"]
    assert list_stacks(tmp_path / "b") == [tmp_path / "b"]
    with pytest.raises(FileNotFoundError):
        list_stacks(tmp_path / "missing")


# ----------------------------------------------------------------------------- synthetic

def test_synthetic_images_have_cumulative_noise_and_clean_quick():
    spp = [16, 64, 256, 1024]
    ref, quick, levels = synthetic_images(64, spp, seed=3, noise=0.15)
    assert ref.shape == quick.shape == (64, 64, 3) and levels.shape == (4, 64, 64, 3)
    assert levels.min() >= 0
    std = [float(np.std(lev - ref)) for lev in levels]
    for a, b in zip(std, std[1:]):
        assert 1.7 < a / b < 2.3          # 1/sqrt(spp): x4 spp -> /2 noise
    # cumulative means: successive levels are strongly correlated
    corr = np.corrcoef((levels[2] - ref).ravel(), (levels[3] - ref).ravel())[0, 1]
    assert corr > 0.35
    # quick is noise-free: smooth (tiny pixel-to-pixel steps)
    assert np.abs(np.diff(quick, axis=1)).max() < 0.05
    again = synthetic_images(64, spp, seed=3, noise=0.15)
    np.testing.assert_array_equal(again[2], levels)


def test_make_synthetic_stack(tmp_path):
    st = make_synthetic_stack(tmp_path / "syn", seed=0)
    assert read_stack(tmp_path / "syn") == st
    assert st.labeler["name"] == "flip" and len(st.thresholds) == 16
    known = [t for t in st.thresholds if t is not None]
    assert len(set(known)) >= 3 and None in st.thresholds   # a spread, and censored blocks
    fixed = make_synthetic_stack(tmp_path / "fix", size=32, spp=[1, 2], thresholds=[2] * 16)
    assert fixed.labeler == {"name": "synthetic"} and fixed.thresholds == [2] * 16
    plain = make_synthetic_stack(tmp_path / "plain", size=32, spp=[1, 2], label=False)
    assert plain.thresholds is None
    shutil.rmtree(tmp_path / "plain")
