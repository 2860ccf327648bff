"""Dataset building: format, labels, resume after interruption, the Dask path."""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from learning import check_dataset, read_stack
from renderer.dataset import stackbuild
from renderer.dataset.stackbuild import BuildSettings, build_stack

TINY = BuildSettings(resolution=32, step=4, levels=4, reference_spp=128, contact_sheet=False)


@pytest.mark.slow
def test_build_writes_a_valid_labelled_stack(tmp_path):
    summary = build_stack("cornell", tmp_path, TINY, progress=False)
    stack = read_stack(tmp_path / "cornell")
    assert stack.spp == [4, 8, 12, 16] and stack.reference_spp == 128
    assert stack.quick_description == "albedo aov, 16 spp"
    assert len(stack.thresholds) == 16 and stack.labeler["name"] == "flip"
    assert summary["levels"] == 4 and summary["blocks"] == 16
    assert check_dataset(tmp_path) == []
    assert not (tmp_path / "cornell" / ".build").exists()
    # levels are cumulative means: each one is closer to the reference than the first
    ref = stack.reference()
    err = [float(np.mean((stack.level(k) - ref) ** 2)) for k in range(4)]
    assert err[-1] < err[0]


@pytest.mark.slow
def test_interrupted_build_resumes_to_the_same_stack(tmp_path, monkeypatch):
    build_stack("cornell", tmp_path / "whole", TINY, progress=False)

    calls = {"n": 0}
    real = stackbuild._save_checkpoint

    def dying(path, level, total):
        real(path, level, total)
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt  # the user pressed ctrl-c after level 2
    monkeypatch.setattr(stackbuild, "_save_checkpoint", dying)
    with pytest.raises(KeyboardInterrupt):
        build_stack("cornell", tmp_path / "cut", TINY, progress=False)
    monkeypatch.setattr(stackbuild, "_save_checkpoint", real)
    assert not (tmp_path / "cut" / "cornell" / "meta.json").exists()
    summary = build_stack("cornell", tmp_path / "cut", TINY, progress=False)
    assert summary["resumed"]
    a, b = read_stack(tmp_path / "whole" / "cornell"), read_stack(tmp_path / "cut" / "cornell")
    for k in range(a.n_levels):
        np.testing.assert_allclose(b.level(k), a.level(k), rtol=1e-5, atol=1e-6)
    assert a.thresholds == b.thresholds


@pytest.mark.slow
def test_dask_local_cluster_of_two_workers(tmp_path):
    from renderer.dataset.build import build_dataset
    summary = build_dataset(["cornell", "sky"], tmp_path, TINY, workers=2, progress=False)
    assert summary["failed"] == {}
    assert [r["scene"] for r in summary["scenes"]] == ["cornell", "sky"]
    assert summary["sub_images"] == 2 * 4 * 16
    assert check_dataset(tmp_path) == []
    # a flat sky is converged at the first level everywhere
    assert read_stack(tmp_path / "sky").thresholds == [4] * 16
    # every run is on record; the bench reports the latest run that rendered anything
    from renderer.dataset.build import read_build_log
    from benchmarks.bench_models import bench_dataset, md_dataset
    again = build_dataset(["cornell", "sky"], tmp_path, TINY, workers=1, progress=False)
    assert all(r["already_built"] for r in again["scenes"])
    runs = read_build_log(tmp_path)
    assert len(runs) == 2 and runs[0]["wall_s"] == pytest.approx(summary["wall_s"])
    reported = bench_dataset(str(tmp_path))
    assert list(reported) == ["training"] and reported["training"]["finished"] == summary["finished"]
    assert "| sky |" in md_dataset(reported) and "128 labelled sub-images" in md_dataset(reported)
    both = bench_dataset(str(tmp_path), str(tmp_path))          # the held-out dataset's run too
    assert list(both) == ["training", "heldout"] and "Held-out scenes" in md_dataset(both)


def test_dataset_without_a_build_log_is_a_clear_error(tmp_path):
    from renderer.dataset.build import BUILD_LOG
    from benchmarks.bench_models import bench_dataset
    with pytest.raises(ValueError, match="no build run on record"):
        bench_dataset(str(tmp_path))
    (tmp_path / BUILD_LOG).write_text('{"scenes": [{"already_built": true}]}\n{"cut sh')
    with pytest.raises(ValueError, match="make dataset"):
        bench_dataset(str(tmp_path))


def test_bad_settings_are_rejected():
    with pytest.raises(ValueError, match="step must be a positive integer"):
        BuildSettings(step=0)


@pytest.mark.slow
def test_exr_write_survives_worker_thread_setup(tmp_path):
    """Regression: drjit.set_thread_count(1) made Mitsuba's EXR writer hang forever."""
    code = (
        "import os, numpy as np\n"
        "os.environ['NOISESTOP_THREADS'] = '1'\n"
        "from learning.data.variant import select_variant; select_variant()\n"
        "from renderer.farm import configure_worker_threads; configure_worker_threads()\n"
        "from learning.data.exr import write_exr\n"
        f"write_exr({str(tmp_path / 'x.exr')!r}, np.ones((16, 16, 3), np.float32))\n"
        "print('written')\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env={**os.environ})
    assert out.returncode == 0 and "written" in out.stdout, out.stderr
