"""What a hostile user or a broken disk can hand the code, one test each: halves that disagree
completely, forged checkpoints, every file through one door (devices, FIFOs, huge sparse
files, zip bombs) and the parse pool's deadlines."""
from __future__ import annotations

import os

import numpy as np
import pytest

from learning.models.bundle import load_model
from renderer.criteria import UnitView, FlipCriterion

GREY = np.full((1, 64, 64, 3), 0.5, np.float32)
#: (even, odd) pairs whose halves disagree completely: noisy, however flat their mean
DISAGREE = {
    "NaN against grey": (np.full_like(GREY, np.nan), GREY),
    "1e38 against 0": (np.full_like(GREY, 1e38), np.zeros_like(GREY)),
    "+3.4e38 against -3.4e38": (np.full_like(GREY, 3.4e38), np.full_like(GREY, -3.4e38)),
    "-Inf against grey": (np.full_like(GREY, -np.inf), GREY),
    "black against white": (np.zeros_like(GREY), np.ones_like(GREY)),
}


@pytest.fixture(scope="module")
def halves_model():
    model = load_model()                      # the bundled model reads the half buffers
    assert model.needs_halves
    return model


@pytest.mark.parametrize("case", sorted(DISAGREE))
def test_disagreeing_halves_are_noisy_on_the_served_route(halves_model, case: str) -> None:
    """The halves route (the server's `assess_halves`) answers -1 for halves that disagree
    completely; control: two equal grey halves are flat, +1."""
    even, odd = DISAGREE[case]
    verdict, _, _ = halves_model.assess_halves(even, odd)
    assert verdict.tolist() == [-1], case
    assert halves_model.assess_halves(GREY, GREY.copy())[0].tolist() == [1]


@pytest.mark.parametrize("case", sorted(DISAGREE))
def test_disagreeing_halves_are_noisy_in_the_local_criteria(case: str) -> None:
    """The live loop's criteria follow the same rule: a flat mean over halves that disagree
    is not flat. Control: equal halves under the same mean are."""
    even, odd = DISAGREE[case]
    crit = FlipCriterion(0.05, tau=0.02)
    mean = GREY[0].astype(np.float64)        # what a mean of the halves may look like: flat
    view = UnitView(mean=mean, spp=2, halves=(even[0], odd[0]), half_spp=(1, 1))
    assert crit.decide([0], [view]).verdict.tolist() == [-1], case
    same = UnitView(mean=mean, spp=2, halves=(GREY[0], GREY[0].copy()), half_spp=(1, 1))
    assert crit.decide([0], [same]).verdict.tolist() == [1]


# --- forged checkpoints: validated by meaning, not only by shape ----------------------------

FORGERIES = {
    "sums x 1e300": lambda a: a.update(acc_sum=a["acc_sum"] * 1e300),
    "sums negated": lambda a: a.update(acc_sum=-a["acc_sum"]),
    "a weight above its samples": lambda a: a["acc_weight"].__setitem__((0, 0, 0, 0), a["acc_weight"].max() + 1),
    "a weight short in a block that dropped nothing": lambda a: a["acc_weight"].__setitem__((0, 0, 0, 0), 0),
    "a ratio of +Inf": lambda a: a["budget_ratio"].__setitem__(np.flatnonzero(a["budget_ratio_asked"])[0], np.inf),
    "a budget cost off the samples": lambda a: a["budget_cost"].__setitem__(1, a["budget_cost"][1] + 16),
}


@pytest.fixture(scope="module")
def budget_checkpoint(tmp_path_factory):
    """A finished budget render's folder (its checkpoint kept) and its report."""
    from renderer.live.adaptive import adaptive_render
    from renderer.criteria import VarianceCriterion

    out = tmp_path_factory.mktemp("forge") / "ok"
    opts = {"resolution": 32, "grid": (4, 4), "step": 4, "min_spp": 4, "max_spp": 24, "progress": False,
            "checkpoint_every": 0.0, "spp_budget": 12}
    report = adaptive_render("cornell", out, VarianceCriterion(0.05), **opts)
    return out, opts, report


@pytest.mark.parametrize("forgery", sorted(FORGERIES))
def test_a_forged_checkpoint_with_a_fresh_digest_is_refused(tmp_path, budget_checkpoint, forgery: str) -> None:
    """Each forgery keeps every shape and type and recomputes the digest (what a forger
    does); resuming from it is refused in one line naming the file. Control: the checkpoint
    as written resumes."""
    import shutil

    from learning.data.npz import read_npz, savez_bytes
    from renderer.live.adaptive import adaptive_render
    from renderer.live.checkpoint import CHECKPOINT
    from renderer.criteria import VarianceCriterion

    src, opts, report = budget_checkpoint
    out = tmp_path / "run"
    shutil.copytree(src, out)
    assert adaptive_render("cornell", out, VarianceCriterion(0.05), resume=True, **opts)["passes"] == report["passes"]
    arrays = read_npz(out / CHECKPOINT)
    arrays.pop("sha256")
    FORGERIES[forgery](arrays)
    (out / CHECKPOINT).write_bytes(savez_bytes(arrays, with_digest=True))
    with pytest.raises(ValueError) as err:
        adaptive_render("cornell", out, VarianceCriterion(0.05), resume=True, **opts)
    assert str(out / CHECKPOINT) in str(err.value) and "\n" not in str(err.value), forgery


@pytest.mark.parametrize("kind", ["/dev/zero", "FIFO"])
def test_a_checkpoint_that_is_a_device_or_a_fifo_is_refused_at_once(tmp_path, kind: str) -> None:
    """`--resume` with checkpoint.npz linked to /dev/zero (it grew to 23.5 GB) or a FIFO (it
    waited for ever): one line naming the file, before anything is read."""
    from renderer.live.adaptive import adaptive_render
    from renderer.live.checkpoint import CHECKPOINT
    from renderer.criteria import VarianceCriterion

    out = tmp_path / "run"
    out.mkdir()
    if kind == "FIFO":
        os.mkfifo(out / CHECKPOINT)
    else:
        os.symlink("/dev/zero", out / CHECKPOINT)
    with pytest.raises(ValueError) as err:
        adaptive_render("cornell", out, VarianceCriterion(0.05), resume=True, resolution=32, grid=(4, 4),
                        step=4, max_spp=8, progress=False)
    assert str(out / CHECKPOINT) in str(err.value) and "not a regular file" in str(err.value)


# --- every file through one door: devices, FIFOs, huge sparse files, zip bombs --------------

def _bad_file(path, kind: str) -> None:
    """Put a /dev/zero link, a FIFO or a 3 GB sparse file at `path`."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.exists() or path.is_symlink():
        path.unlink()
    if kind == "/dev/zero":
        os.symlink("/dev/zero", path)
    elif kind == "FIFO":
        os.mkfifo(path)
    else:
        with open(path, "wb") as f:
            f.truncate(3 << 30)


BAD = ("/dev/zero", "FIFO", "3 GB sparse")


def _refused_in_one_line(call, path, seconds: float = 60.0) -> str:
    """The call's one-line refusal naming `path`. `seconds` only tells a refusal from a hang
    (a busy machine may take seconds to load what precedes it); the refusal's speed is
    BENCHMARKS.md's (bench hardening), not a unit test's."""
    import time

    t0 = time.perf_counter()
    with pytest.raises((ValueError, OSError)) as err:
        call()
    assert time.perf_counter() - t0 < seconds
    msg = str(err.value)
    assert str(path) in msg and "\n" not in msg, msg
    return msg


@pytest.mark.parametrize("kind", BAD)
def test_feature_weights_that_are_not_a_small_regular_file_are_refused(tmp_path, kind: str) -> None:
    from noisefeat.weights import load_kernels

    path = tmp_path / "weights.safetensors"
    _bad_file(path, kind)
    _refused_in_one_line(lambda: load_kernels(path), path)


@pytest.mark.parametrize("member", ["model.skops", "manifest.json"])
@pytest.mark.parametrize("kind", BAD)
def test_bundle_members_that_are_not_small_regular_files_are_refused(tmp_path, member: str, kind: str) -> None:
    """A bundle member linked to /dev/zero, a FIFO, or a 3 GB sparse file (it was hashed
    for 18 s, or read whole): refused before it is read, naming the member."""
    import shutil

    from learning.models.bundle import BUNDLED_DIR, load_model

    bundle = tmp_path / "b"
    shutil.copytree(BUNDLED_DIR, bundle)
    _bad_file(bundle / member, kind)
    _refused_in_one_line(lambda: load_model(bundle), bundle / member)


def test_a_skops_zip_bomb_is_refused_before_it_inflates(tmp_path) -> None:
    """schema.json inflating to 200 MiB of whitespace (a 200 KB file, its hash in the
    manifest, so only the size can catch it): refused from the zip headers, before any
    member is inflated. Control: the bundled model loads from a copy."""
    import hashlib
    import json
    import shutil
    import zipfile

    from learning.models.bundle import BUNDLED_DIR, load_model

    bundle = tmp_path / "b"
    shutil.copytree(BUNDLED_DIR, bundle)
    assert load_model(bundle).needs_halves
    with zipfile.ZipFile(BUNDLED_DIR / "model.skops") as src, \
            zipfile.ZipFile(bundle / "model.skops", "w", zipfile.ZIP_DEFLATED) as dst:
        for info in src.infolist():
            data = src.read(info)
            if info.filename == "schema.json":
                data = data[:-1] + b" " * (200 << 20) + data[-1:]
            dst.writestr(info.filename, data)
    assert (bundle / "model.skops").stat().st_size < (2 << 20)
    manifest = json.loads((bundle / "manifest.json").read_text())
    manifest["model_sha256"] = hashlib.sha256((bundle / "model.skops").read_bytes()).hexdigest()
    (bundle / "manifest.json").write_text(json.dumps(manifest))
    msg = _refused_in_one_line(lambda: load_model(bundle), bundle / "model.skops")
    assert "refused before inflating" in msg


def test_an_npz_bomb_is_refused_before_it_inflates(tmp_path) -> None:
    """An .npz whose one member inflates to 200 MiB of zeros (a 200 KB file): refused from
    its headers at a checkpoint's size bound."""
    import io
    import zipfile

    from learning.data.npz import read_npz

    buf = io.BytesIO()
    np.save(buf, np.zeros(200 << 17))            # 200 MiB of float64 zeros
    path = tmp_path / "bomb.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("a.npy", buf.getvalue())
    assert path.stat().st_size < (1 << 20)
    msg = _refused_in_one_line(lambda: read_npz(path, max_bytes=64 << 20, kind="checkpoint"), path)
    assert "unpacks to" in msg


@pytest.mark.parametrize("kind", ["symlink", "FIFO"])
def test_a_lock_file_that_is_a_link_or_a_fifo_names_itself(tmp_path, kind: str) -> None:
    from renderer.live.outlock import LOCK_NAME, locked_output

    out = tmp_path / "out"
    out.mkdir()
    if kind == "FIFO":
        os.mkfifo(out / LOCK_NAME)
    else:
        os.symlink(tmp_path / "elsewhere", out / LOCK_NAME)

    def hold() -> None:
        with locked_output(out):
            pass
    msg = _refused_in_one_line(hold, out / LOCK_NAME)
    assert "remove it" in msg


def test_an_input_whose_read_fails_is_named(tmp_path) -> None:
    """/proc/self/mem passes as a regular file of size 0 and its read fails with a bare
    "[Errno 5] Input/output error": the error names the file."""
    import shutil

    from learning.models.bundle import BUNDLED_DIR, load_model

    if not os.path.exists("/proc/self/mem"):
        pytest.skip("no /proc")
    bundle = tmp_path / "b"
    shutil.copytree(BUNDLED_DIR, bundle)
    (bundle / "manifest.json").unlink()
    os.symlink("/proc/self/mem", bundle / "manifest.json")
    msg = _refused_in_one_line(lambda: load_model(bundle), bundle / "manifest.json")
    assert "cannot be read" in msg


def test_dataset_check_reports_an_unreadable_meta_json_as_that_stacks_problem(tmp_path) -> None:
    """A FIFO or /proc/self/mem as a stack's meta.json: a problem of that stack, the others
    checked (it exited 2 before)."""
    import shutil

    from learning.data.check import check_dataset

    root = tmp_path / "d"
    shutil.copytree("tests/fixtures/dataset", root)
    stacks = sorted(p for p in root.iterdir() if (p / "meta.json").exists())
    os.unlink(stacks[0] / "meta.json")
    os.mkfifo(stacks[0] / "meta.json")
    if os.path.exists("/proc/self/mem"):
        os.unlink(stacks[1] / "meta.json")
        os.symlink("/proc/self/mem", stacks[1] / "meta.json")
    problems = check_dataset(root)
    where = {str(p.path) for p in problems}
    assert str(stacks[0] / "meta.json") in where
    assert any("FIFO" in p.message for p in problems)


# --- the parse pool: every sizeable JSON body off the event loop, deadlines both ways -------

@pytest.fixture(scope="module")
def demo_bundle(tmp_path_factory):
    from tests.support.demo import make_demo_bundle

    return str(make_demo_bundle(tmp_path_factory.mktemp("r4") / "demo", name="demo"))


def test_a_stopped_parse_worker_costs_a_request_its_budget_not_for_ever(demo_bundle) -> None:
    """Both workers stopped (SIGSTOP): a large JSON request is answered 413 once its parse
    budget runs out (the write into the worker had no deadline: it hung past 120 s and
    kept its slot), and a binary request is served meanwhile; then fresh workers serve it.

    Load-proof: the stopped phase asserts an answer, not how fast the deadline fired (the
    bound is far from the budget and far below the old hang); the served phase gives the
    pool a generous budget, since it includes starting a new worker, which a busy machine
    can take seconds to do (the budget's timing is BENCHMARKS.md's, not a unit test's)."""
    import signal
    import time

    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.registry import ModelRegistry
    from tests.support.demo import make_request

    app = create_app(ModelRegistry({"demo": demo_bundle}), parse_seconds=1.0)
    body, headers = make_request(blocks=16, size=64, binary=False)          # ~1 MB of JSON: the pool's
    small, small_headers = make_request(blocks=1, size=64, binary=True)
    with TestClient(app) as c:
        pool = app.state.parse_pool
        pids = [w.proc.pid for w in pool._idle]
        assert len(pids) == 2
        for pid in pids:
            os.kill(pid, signal.SIGSTOP)
        try:
            for _ in range(2):
                t0 = time.monotonic()
                r = c.post("/v2/models/default/infer", content=body, headers=headers)
                assert r.status_code in (413, 503), r.text        # the budget ran out, or the worker was ended
                assert time.monotonic() - t0 < 60          # the deadline's answer, not the old hang
            assert all(w.proc.pid not in pids for w in pool._idle)     # both stopped workers ended
            assert c.post("/v2/models/default/infer", content=small, headers=small_headers).status_code == 200
        finally:
            for pid in pids:
                try:
                    os.kill(pid, signal.SIGCONT)
                except ProcessLookupError:
                    pass
        pool.seconds = 120.0              # a new worker starts within it on any machine
        assert c.post("/v2/models/default/infer", content=body, headers=headers).status_code == 200


def test_an_idle_parse_worker_that_dies_is_reaped_and_replaced_at_once(demo_bundle) -> None:
    """A worker killed while idle stayed a zombie until its slot was used again: now it is
    reaped (no zombie left) and a new worker takes its place at once, with no request needed
    (polled for its state; how soon is the reaper's period, not asserted here)."""
    import signal
    import time

    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.registry import ModelRegistry

    app = create_app(ModelRegistry({"demo": demo_bundle}))
    with TestClient(app):
        pool = app.state.parse_pool
        victim = pool._idle[0].proc
        os.kill(victim.pid, signal.SIGKILL)
        deadline = time.monotonic() + 60.0        # polled: done in well under a second unless the box is busy
        while time.monotonic() < deadline and (victim.returncode is None or len(pool._idle) < 2):
            time.sleep(0.05)
        assert victim.returncode is not None                       # waited for: not a zombie
        with pytest.raises(ChildProcessError):
            os.waitpid(victim.pid, os.WNOHANG)
        assert len(pool._idle) == 2 and all(w.alive() for w in pool._idle)
        assert victim.pid not in [w.proc.pid for w in pool._idle]


@pytest.mark.parametrize("kind", ["/dev/zero", "FIFO"])
def test_a_scene_file_that_is_a_device_or_a_fifo_is_refused(tmp_path, kind: str) -> None:
    """Mitsuba reads the scene XML itself: a FIFO there would hang it, so the path is
    checked through safeio first."""
    from renderer.scenes.catalog import load_scene

    path = tmp_path / "scene.xml"
    _bad_file(path, kind)
    _refused_in_one_line(lambda: load_scene(str(path)), path)
