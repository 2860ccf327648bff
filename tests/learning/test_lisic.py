"""Import of LISIC-layout datasets (synthetic trees built in tmp_path)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from learning.data.check import ERROR, check_dataset
from learning.data.exr import write_png
from learning.data.frame_flip import display
from learning.data.lisic import import_lisic, read_config, scan_scene
from learning.data.stack import read_stack

SPP = [20, 40, 60, 80, 100]


def _png(seed: int, size: int = 64) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (size, size, 3), dtype=np.uint8)


def make_scene(root: Path, name: str, seed: int = 0, spp=SPP, size: int = 64,
               thresholds=None, config: bool = True) -> Path:
    d = root / name
    d.mkdir(parents=True)
    for i, s in enumerate(spp):
        write_png(d / f"{name}_{s:05d}.png", _png(seed * 100 + i, size))
    th = thresholds if thresholds is not None else [20 + 7 * z for z in range(16)]
    for z, t in enumerate(th):
        (d / f"zone{z:02d}").mkdir()
        (d / f"zone{z:02d}" / "seuilExpe").write_text(f"{t}\n")
    if config:
        step = spp[1] - spp[0]
        (d / "config").write_text(f"{name}_{spp[-1]:05d}.png\n{name}_\n{spp[0]:05d}\n"
                                  f"{spp[-1]:05d}\n{step}\n")
    return d


@pytest.fixture
def tree(tmp_path):
    src = tmp_path / "lisic"
    make_scene(src, "Cuisine01", seed=1)
    make_scene(src, "SdbDroite", seed=2, config=False,
               thresholds=[404, 320, 163, 375, 439, 309, 192, 330, 467, 387, 221, 256, 305,
                           184, 210, 219])
    (src / "README").write_text("not a scene")
    return src


def test_import_two_scenes(tree, tmp_path):
    out = tmp_path / "out"
    dirs = import_lisic(tree, out)
    assert dirs == [out / "Cuisine01", out / "SdbDroite"]
    st = read_stack(out / "Cuisine01")
    assert st.spp == SPP and st.reference_spp == 100 and (st.width, st.height) == (64, 64)
    assert st.thresholds == [20 + 7 * z for z in range(16)]
    assert st.labeler == {"name": "human", "source": "LISIC"}
    assert st.quick_description == "none" and not (out / "Cuisine01" / "quick.exr").exists()
    assert "display-referred" in st.extras["import"]
    # levels are linear: the display transform gives the PNG back exactly
    for k in range(len(SPP)):
        back = np.round(display(st.level(k)) * 255).astype(np.uint8)
        np.testing.assert_array_equal(back, _png(100 + k))
    np.testing.assert_array_equal(st.reference(), st.level(-1))
    assert float(st.level(0).max()) <= 1.0 and float(st.level(0).mean()) < 0.4  # linear, not sRGB
    sdb = read_stack(out / "SdbDroite")
    assert sdb.thresholds[:3] == [404, 320, 163]
    labels = sdb.labels()
    assert labels.shape == (5, 16) and np.all(labels == -1)  # every threshold above 100 spp
    # the checker accepts the import: only warnings (human thresholds between levels)
    problems = check_dataset(out)
    assert problems and all(p.severity != ERROR for p in problems)


def test_import_resumes_and_is_idempotent(tree, tmp_path):
    out = tmp_path / "out"
    import_lisic(tree, out, scenes=["Cuisine01"])
    d = out / "Cuisine01"
    meta = json.loads((d / "meta.json").read_text())
    # simulate an interruption: meta.json not yet written, one level missing
    (d / "meta.json").unlink()
    (d / "meta.partial.json").write_text(json.dumps(
        {k: v for k, v in meta.items() if k not in ("labeler", "thresholds")}))
    (d / "levels" / "000060.exr").unlink()
    import_lisic(tree, out, scenes=["Cuisine01"])
    st = read_stack(d)
    np.testing.assert_array_equal(np.round(display(st.level(2)) * 255).astype(np.uint8),
                                  _png(102))
    assert not (d / "meta.partial.json").exists()
    import_lisic(tree, out, scenes=["Cuisine01"])  # complete: nothing to redo
    assert read_stack(d) == st


def test_every_keeps_the_reference_level(tree, tmp_path):
    (d,) = import_lisic(tree, tmp_path / "out", scenes=["Cuisine01"], every=3)
    assert read_stack(d).spp == [20, 80, 100]


def test_config_parsing(tmp_path):
    p = tmp_path / "config"
    p.write_text("X_01200.png\nX_\n00020\n01200\n20\n")
    assert read_config(p) == ("X_", 20, 1200, 20, 5)
    p.write_text("X_01200.png\nX_\n00020\n")
    with pytest.raises(ValueError, match="expected 5 lines"):
        read_config(p)
    p.write_text("X_01200.png\nX_\n00020\n01200\ntwenty\n")
    with pytest.raises(ValueError, match="must be integers"):
        read_config(p)


def test_missing_zone(tmp_path):
    d = make_scene(tmp_path, "S")
    (d / "zone05" / "seuilExpe").unlink()
    (d / "zone05").rmdir()
    with pytest.raises(FileNotFoundError, match="zone05"):
        scan_scene(d)


def test_missing_threshold_file_and_bad_integers(tmp_path):
    d = make_scene(tmp_path, "S")
    f = d / "zone03" / "seuilExpe"
    f.write_text("about 300\n")
    with pytest.raises(ValueError, match=r"zone03/seuilExpe.*one integer"):
        scan_scene(d)
    f.write_text("-5\n")
    with pytest.raises(ValueError, match="positive"):
        scan_scene(d)
    f.write_text("")
    with pytest.raises(ValueError, match="empty"):
        scan_scene(d)
    f.unlink()
    with pytest.raises(FileNotFoundError, match="zone03/seuilExpe"):
        scan_scene(d)


def test_extra_zones_are_an_error(tmp_path):
    d = make_scene(tmp_path, "S")
    (d / "zone16").mkdir()
    with pytest.raises(ValueError, match="zone16"):
        scan_scene(d)


def test_images_of_different_sizes(tmp_path):
    d = make_scene(tmp_path / "src", "S")
    write_png(d / "S_00060.png", _png(5, size=32))
    with pytest.raises(ValueError, match="S_00060.png.*S_00020.png"):
        import_lisic(tmp_path / "src", tmp_path / "out")


def test_non_increasing_spp(tmp_path):
    d = make_scene(tmp_path / "a", "S")
    (d / "config").write_text("S_00100.png\nS_\n00100\n00020\n20\n")
    with pytest.raises(ValueError, match="increasing spp"):
        scan_scene(d)
    (d / "config").write_text("S_00100.png\nS_\n00020\n00100\n0\n")
    with pytest.raises(ValueError, match="increasing spp"):
        scan_scene(d)
    e = make_scene(tmp_path / "b", "T", config=False)
    write_png(e / "T_0020.png", _png(9))   # same spp as T_00020.png
    with pytest.raises(ValueError, match="two images for spp 20"):
        scan_scene(e)


def test_image_listed_in_config_missing(tmp_path):
    d = make_scene(tmp_path, "S")
    (d / "S_00060.png").unlink()
    with pytest.raises(FileNotFoundError, match="S_00060.png"):
        scan_scene(d)


def test_size_not_divisible_by_grid(tmp_path):
    make_scene(tmp_path / "src", "S", size=30)
    with pytest.raises(ValueError, match="S_00020.png.*cannot be cut"):
        import_lisic(tmp_path / "src", tmp_path / "out")


def test_non_strict_skips_bad_scenes(tree, tmp_path):
    (tree / "Cuisine01" / "zone00" / "seuilExpe").write_text("x")
    with pytest.raises(ValueError, match="seuilExpe"):
        import_lisic(tree, tmp_path / "out")
    dirs = import_lisic(tree, tmp_path / "out2", strict=False)
    assert dirs == [tmp_path / "out2" / "SdbDroite"]


def test_bad_sources(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such"):
        import_lisic(tmp_path / "none", tmp_path / "out")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no LISIC scene"):
        import_lisic(tmp_path / "empty", tmp_path / "out")
    make_scene(tmp_path / "src", "S")
    with pytest.raises(ValueError, match="no LISIC scene named Nope"):
        import_lisic(tmp_path / "src", tmp_path / "out", scenes=["Nope"])
    # a scene directory given directly works too
    assert import_lisic(tmp_path / "src" / "S", tmp_path / "out") == [tmp_path / "out" / "S"]
