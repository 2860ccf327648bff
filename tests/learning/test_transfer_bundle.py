"""The transfer baselines trained, bundled, loaded, evaluated, rendered and served
end to end, through the one stop rule; damaged bundles refused with one line."""
from __future__ import annotations

import json
import shutil
import socket
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch
from fastapi.testclient import TestClient

from tests.support.extremes import CASES, extreme_halves
from learning.evaluation.evaluate import stops_by_scene
from learning.evaluation.metrics import stop_thresholds
from learning.inputs.pictures import noise_picture
from learning.inputs.table import rgb_blocks
from learning.inputs.table import load_table
from learning.models import transfer_archs as T
from learning.models.bundle import load_model
from learning.models.transfer_bundle import TransferModel, save_transfer_model
from learning.names import MODEL_KINDS, TRANSFER_KINDS
from learning.training import compare
from learning.training.train_transfer import train_transfer
from renderer.criteria import ModelCriterion
from renderer.simulation.simulate import simulate_loop
from service.app import create_app
from service.cli import main
from service.registry import ModelRegistry
from tests.support import FIXTURE_DATASET as FIXTURE

ARCH = "mobilenet_v2"           # the smallest base: tests stay fast
TRAIN = ["checker", "cornell_dark"]
TEST = ["cornell", "sky"]
TOKEN = "test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def _offline(mp: pytest.MonkeyPatch, home: Path) -> None:
    """An empty hub cache, one torch thread (restored by the caller), and no network."""
    def refuse(*args, **kwargs):
        raise AssertionError(f"network access attempted: {args[:2]}")
    mp.setenv("TORCH_HOME", str(home))
    mp.setattr(torch.hub, "load_state_dict_from_url", refuse)
    mp.setattr(urllib.request, "urlopen", refuse)
    mp.setattr(socket.socket, "connect", refuse)


@pytest.fixture(scope="module", autouse=True)
def offline(tmp_path_factory):
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    with pytest.MonkeyPatch.context() as mp:
        _offline(mp, tmp_path_factory.mktemp("torch_home"))
        yield
    torch.set_num_threads(threads)


def _train(quick: str, out: Path, weights: str | None = None, calibrate: bool = True):
    table = load_table(FIXTURE, image=True, quick=quick, progress=False)
    clf, summary = train_transfer(ARCH, str(FIXTURE), quick=quick, weights=weights, table=table,
                                  test_scenes=TEST, max_early_stop=0.05 if calibrate else None,
                                  epochs=4, batch_size=64, progress=False)
    save_transfer_model(clf, out, quick=quick, training=summary)
    return clf, table


@pytest.fixture(scope="module", params=["halves", "none"])
def trained(request, tmp_path_factory):
    """(classifier before saving, its bundle's path, the fixture's picture table)."""
    out = tmp_path_factory.mktemp("tb") / request.param
    clf, table = _train(request.param, out)
    return clf, out, table


def test_one_tuple_of_transfer_kinds():
    assert tuple(T.ARCHS) == TRANSFER_KINDS
    assert compare.TRANSFER_ARCHES is TRANSFER_KINDS
    assert set(TRANSFER_KINDS) <= set(MODEL_KINDS)


def test_pictures_keep_the_comparisons_input(trained):
    """rgb_blocks (moved out of compare) gives a table's rows as the picture table holds them."""
    _, path, table = trained
    sub = table.subset(table.scene == "cornell")
    pics = rgb_blocks(sub, halves=load_model(path).needs_halves)
    np.testing.assert_array_equal(pics, sub.X)


def test_bundle_round_trip_keeps_decisions(trained):
    clf, path, table = trained
    model = load_model(path)
    assert isinstance(model, TransferModel) and model.input == "image"
    assert model.manifest["kind"] == ARCH and model.manifest["quick"] in ("halves", "none")
    assert model.label == f"{ARCH} (untrained base)" == model.manifest["base"]["label"]
    assert model.offset == clf.offset_ == model.manifest["offset"]
    assert model.manifest["training"]["calibration"]["target_early_stop_rate"] == 0.05
    assert model.block_shape == (16, 16) and model.table_options() == {"image": True, "quick": model.quick}
    X = table.X[::7]
    np.testing.assert_allclose(model.decision_function(X), clf.decision_function(X), rtol=0, atol=1e-6)
    assert sorted(p.name for p in path.iterdir()) == ["manifest.json", "transfer.json", "transfer.safetensors"]


def test_evaluate_command_on_a_transfer_bundle(trained, capsys, tmp_path):
    _, path, table = trained
    assert main(["evaluate", "--data", str(FIXTURE), "--model", str(path), "--plots", str(tmp_path),
                 "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert sorted(got["per_scene"]) == TEST            # the scenes it was not trained on
    assert 0 <= got["precision"] <= 1 and got["offset"] == load_model(path).offset
    assert got["n_sub_images"] == int(np.isin(table.scene, TEST).sum())


def test_train_command_trains_and_bundles(tmp_path, capsys):
    out = tmp_path / "m"
    assert main(["train", "--data", str(FIXTURE), "--model", ARCH, "--input", "none", "--test-scenes",
                 ",".join(TEST), "--no-calibrate", "--out", str(out), "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got["kind"] == ARCH and got["base"] == f"{ARCH} (untrained base)" and got["input"] == "none"
    assert got["offset"] == 0.0 and got["test_scenes"] == TEST and 0 <= got["precision"] <= 1
    model = load_model(out)
    assert model.quick == "none" and model.manifest["metrics"]["precision"] == got["precision"]
    blocks = np.random.default_rng(0).random((3, 16, 16, 3), dtype=np.float32)
    verdict, score = model.score_blocks(blocks)
    assert verdict.shape == (3,) and np.isfinite(score).all()


@pytest.mark.parametrize("argv, words", [
    (["--model", "vgg19", "--input", "albedo"], "--input halves or none"),
    (["--model", "resnet50", "--input", "direct"], "--input halves or none"),
    (["--model", "vgg19", "--composition", "f"], "no --composition"),
    (["--model", "dsvm", "--weights", "w.pth"], "--weights applies to the transfer baselines"),
])
def test_transfer_usage_errors_are_one_line(argv, words, tmp_path, capsys):
    assert main(["train", "--data", str(FIXTURE), "--out", str(tmp_path / "m"), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert words in err and len(err.splitlines()) == 1
    assert not (tmp_path / "m").exists()


def test_missing_weights_file_is_one_line(tmp_path, capsys):
    assert main(["train", "--data", str(FIXTURE), "--model", ARCH, "--weights", str(tmp_path / "no.pth"),
                 "--out", str(tmp_path / "m")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no.pth: no such file" in err[0]


def _damage_tensors(p: Path) -> None:
    data = bytearray((p / "transfer.safetensors").read_bytes())
    data[-5] ^= 0x55
    (p / "transfer.safetensors").write_bytes(bytes(data))


def _edit_manifest(**changes):
    def edit(p: Path) -> None:
        m = json.loads((p / "manifest.json").read_text())
        m.update(changes)
        (p / "manifest.json").write_text(json.dumps(m))
    return edit


def _edit_state(p: Path) -> None:
    s = json.loads((p / "transfer.json").read_text())
    s["offset"] = -3.0
    (p / "transfer.json").write_text(json.dumps(s))


@pytest.mark.parametrize("damage, words", [
    (_damage_tensors, "transfer.safetensors: content does not match the manifest's model_sha256"),
    (_edit_state, "transfer.json: content does not match the manifest's state_sha256"),
    (_edit_manifest(kind="resnet50"), "holds a 'mobilenet_v2' classifier, the manifest says 'resnet50'"),
    (_edit_manifest(kind="dsvm"), "is not an image classifier"),
    (_edit_manifest(quick="albedo"), "unknown input mode quick='albedo'"),
    (_edit_manifest(offset=2.5), "differs from the manifest's"),
    (_edit_manifest(offset=float("nan")), "offset"),
    (_edit_manifest(model_sha256="0" * 64), "model_sha256 (changed or damaged)"),
    (_edit_manifest(state_sha256=None), "needs state_sha256"),
    (_edit_manifest(block=[32, 32]), "block shape"),
    (lambda p: (p / "transfer.safetensors").unlink(), "transfer.safetensors: missing"),
])
def test_damaged_bundle_is_refused_with_one_line(trained, damage, words, tmp_path, capsys):
    _, path, _ = trained
    bad = tmp_path / "bad"
    shutil.copytree(path, bad)
    damage(bad)
    with pytest.raises((ValueError, FileNotFoundError)) as exc:
        load_model(bad)
    assert words in str(exc.value) and len(str(exc.value).splitlines()) == 1
    assert main(["evaluate", "--data", str(FIXTURE), "--model", str(bad), "--json"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0]


def test_changed_base_weights_are_refused(tmp_path):
    """A frozen pretrained base is referenced by path and SHA-256: changed or gone, refused."""
    weights = tmp_path / "base.pth"
    torch.manual_seed(1)
    torch.save(getattr(T.import_torchvision().models, ARCH)(weights=None).state_dict(), weights)
    out = tmp_path / "m"
    _train("halves", out, weights=str(weights), calibrate=False)
    model = load_model(out)
    assert model.manifest["base"]["weights"] == str(weights) and model.label == f"{ARCH} (weights base.pth)"
    assert len(model.manifest["base"]["weights_sha256"]) == 64
    state = torch.load(weights, weights_only=True)
    next(v for v in state.values() if v.is_floating_point()).add_(1e-3)
    torch.save(state, weights)
    with pytest.raises(ValueError, match="base weights .* changed since training") as exc:
        load_model(out)
    assert len(str(exc.value).splitlines()) == 1
    weights.unlink()
    with pytest.raises(FileNotFoundError, match="are gone"):
        load_model(out)


def test_served_transfer_bundle_answers(trained):
    clf, path, _ = trained
    model = load_model(path)
    app = create_app(ModelRegistry({"tb": str(path)}), token=TOKEN)
    rng = np.random.default_rng(2)
    a = rng.random((3, 16, 16, 3), dtype=np.float32)
    b = rng.random((3, 16, 16, 3), dtype=np.float32)
    a[0, 0, 0, 0] = np.nan
    b[1, 2, 2, 1] = np.inf
    names = ["even", "odd"] if model.needs_halves else ["blocks"]
    arrays = [a, b] if model.needs_halves else [a]
    with TestClient(app) as client:
        meta = client.get("/v2/models/tb", headers=AUTH).json()
        assert meta["platform"] == "noisestop-torch"
        assert [t["name"] for t in meta["inputs"]] == (names if model.needs_halves else ["blocks", "quick"])
        assert meta["parameters"]["input"] == "image" and meta["parameters"]["quick"] == model.quick
        assert meta["parameters"]["base"] == f"{ARCH} (untrained base)" and meta["parameters"]["block"] == [16, 16]
        assert "n_features" not in meta["parameters"]
        # JSON has no NaN: send them through the binary extension instead
        raw = b"".join(x.tobytes() for x in arrays)
        bin_body = {"inputs": [{"name": n, "shape": list(x.shape), "datatype": "FP32",
                                "parameters": {"binary_data_size": x.nbytes}} for n, x in zip(names, arrays)]}
        head = json.dumps(bin_body).encode()
        r = client.post("/v2/models/tb/infer", content=head + raw,
                        headers={**AUTH, "Inference-Header-Content-Length": str(len(head)),
                                 "Content-Type": "application/octet-stream"})
        assert r.status_code == 200, r.text
        out = json.loads(r.content[:int(r.headers.get("Inference-Header-Content-Length", len(r.content)))])
        verdict = next(o for o in out["outputs"] if o["name"] == "verdict")
        assert verdict["shape"] == [3]
        counts = out["parameters"]["nonfinite_pixels"]
        assert counts == ([1, 1, 0] if model.needs_halves else [1, 0, 0])
        want = model.assess_halves(a, b)[0] if model.needs_halves else model.assess_blocks(a)[0]
        assert verdict["data"] == want.tolist()
        # no features input, and only the training block size
        feats = {"inputs": [{"name": "features", "shape": [1, 1280], "datatype": "FP32", "data": [0.0] * 1280}]}
        r = client.post("/v2/models/tb/infer", json=feats, headers=AUTH)
        assert r.status_code == 400 and "has no input 'features'" in r.json()["error"]
        small = {"inputs": [{"name": n, "shape": [1, 32, 32, 3], "datatype": "FP32", "data": [0.1] * 3072}
                            for n in names]}
        r = client.post("/v2/models/tb/infer", json=small, headers=AUTH)
        assert r.status_code == 400 and "takes 16x16 blocks" in r.json()["error"]


@pytest.mark.parametrize("case", CASES)
def test_extreme_inputs_give_verdicts(trained, case):
    """Black and constant blocks are flat: converged at once; fireflies, NaN/Inf, tiny and
    huge values give finite scores and counted non-finite pixels, no crash."""
    _, path, _ = trained
    model = load_model(path)
    rng = np.random.default_rng(3)
    a, b = extreme_halves(case, rng.random((4, 16, 16, 3), dtype=np.float32),
                          rng.random((4, 16, 16, 3), dtype=np.float32))
    if model.needs_halves:
        verdict, score, bad = model.assess_halves(a, b)
        pics = noise_picture(a, b)
        assert np.isfinite(pics).all()
    else:
        verdict, score, counts = model.assess_blocks(a)
        bad = counts["blocks"]
    assert verdict.shape == score.shape == bad.shape == (len(a),)
    assert set(verdict.tolist()) <= {-1, 1} and np.isfinite(score).all()
    if case in ("black", "constant"):
        assert (verdict == 1).all()
    if case == "nan_inf":
        assert bad.sum() >= (3 if model.needs_halves else 2)


def test_simulation_makes_the_evaluate_stops(trained):
    """The criterion code the render loop runs (ModelCriterion on the stack's passes) stops
    the blocks evaluate's rule stops, at the same spp."""
    _, path, table = trained
    model = load_model(path)
    sub = table.subset(table.scene == "cornell")
    stack = sub.stacks["cornell"]
    scores = model.decision_function(sub.X)
    off = float(np.quantile(scores[sub.decidable], 0.5))
    V = stops_by_scene(sub, scores, model.rule(off))["cornell"][0]
    assert len(set(stop_thresholds(V, stack.spp).tolist())) > 2      # blocks stop at several spp
    got, loop = simulate_loop(stack, ModelCriterion(model, offset=off))
    np.testing.assert_array_equal(stop_thresholds(got, stack.spp), stop_thresholds(V, stack.spp))
    assert loop.ledger.counters["units_featured"] > 0


def test_calibration_offsets_follow_the_scores():
    """Logits (and an SVM's scores at another noise target) may run far past the fixed
    offset grid: the offsets tried span them, the grid included."""
    from learning.evaluation.calibrate import DEFAULT_OFFSETS, score_offsets
    scores = np.array([np.nan, -np.inf, -30.0, 2.0, 45.5, 45.5])
    offs = score_offsets(scores, steps=11)
    assert offs == tuple(sorted(set(offs))) and 0.0 in offs and set(DEFAULT_OFFSETS) <= set(offs)
    assert offs[0] == -30.0 and offs[-1] == 45.5
    assert score_offsets(np.array([np.nan])) == tuple(sorted({0.0, *DEFAULT_OFFSETS}))


@pytest.mark.slow
def test_render_with_a_transfer_bundle(trained, tmp_path, capsys):
    """`noisestop render --model M` with a transfer bundle: a real Mitsuba render."""
    _, path, _ = trained
    assert main(["render", "--scene", "cornell", "--model", str(path), "--resolution", "32", "--block", "16",
                 "--step", "16", "--max-spp", "64", "--out", str(tmp_path / "r"), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert len(report["blocks"]) == 4 and report["criterion"]["model"]["input"] == "image"
    assert report["offset"] == load_model(path).offset
    assert all(16 <= b["spp"] <= 64 for b in report["blocks"])
