"""TransferClassifier: estimator contract, weights lookup without network, untrained label."""
from __future__ import annotations

import hashlib
import json
import logging
import socket
import subprocess
import sys
import urllib.request

import numpy as np
import pytest
import torch
from sklearn.base import clone

from learning.models import transfer_archs as A
from learning.models import transfer_state as S
from learning.models import transfer_weights as W
from learning.models.transfer import TransferClassifier

ARCH = "mobilenet_v2"  # the smallest base: tests stay fast


@pytest.fixture(autouse=True)
def offline(monkeypatch, tmp_path):
    """An empty hub cache, one torch thread, and any attempt to reach the network fails."""
    def refuse(*args, **kwargs):
        raise AssertionError(f"network access attempted: {args[:2]}")
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", refuse)
    monkeypatch.setattr(torch.hub, "download_url_to_file", refuse)
    monkeypatch.setattr(urllib.request, "urlopen", refuse)
    monkeypatch.setattr(socket.socket, "connect", refuse)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny batches: threads only add overhead
    yield
    torch.set_num_threads(threads)


def _data(n: int = 32, size: int = 32, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Linear RGB blocks: converged ones smooth, noisy ones speckled."""
    rng = np.random.default_rng(seed)
    y = np.where(np.arange(n) % 2 == 0, 1, -1)
    X = np.full((n, size, size, 3), 0.2, np.float32) + 0.05 * rng.random((n, 1, 1, 3), np.float32)
    X[y < 0] += rng.exponential(0.3, (int((y < 0).sum()), size, size, 3)).astype(np.float32)
    return X, y


def _fit(**kw) -> TransferClassifier:
    X, y = _data()
    params = {"arch": ARCH, "epochs": 15, "batch_size": 16} | kw
    return TransferClassifier(**params).fit(X, y)


def _state_dict_file(path, arch: str = ARCH, seed: int = 1):
    """A torchvision-format state_dict (random weights: no real ImageNet file is available)."""
    torch.manual_seed(seed)
    model = getattr(A.import_torchvision().models, arch)(weights=None)
    torch.save(model.state_dict(), path)
    return path


def test_fit_predict_contract(caplog):
    X, y = _data()
    with caplog.at_level(logging.WARNING, logger="learning.models.transfer"):
        m = TransferClassifier(arch=ARCH, epochs=15, batch_size=16).fit(X, y)
    assert "UNTRAINED" in caplog.text and "random init" in caplog.text
    assert m.base_pretrained_ is False and m.report_label() == f"{ARCH} (untrained base)"
    f = m.decision_function(X)
    assert f.shape == (len(X),) and f.dtype == np.float64 and np.isfinite(f).all()
    pred = m.predict(X)
    assert pred.dtype == np.int8 and set(np.unique(pred)) <= {-1, 1}
    assert np.array_equal(pred, np.where(f > 0, 1, -1))
    assert (pred == y).mean() >= 0.9          # separable toy data: the head learns it
    assert m.loss_curve_[-1] < m.loss_curve_[0]
    assert list(m.classes_) == [-1, 1]
    proba = m.predict_proba(X)
    assert proba.shape == (len(X), 2) and np.allclose(proba.sum(1), 1.0)
    assert np.array_equal(proba[:, 1] > 0.5, f > 0)
    assert m.offset_ == 0.0 and "offset" not in m.get_params()   # fitted, not a parameter
    m.offset_ = float(f.max()) + 1.0          # a larger offset stops later: here never
    assert (m.predict(X) == -1).all()


def test_parameter_counts():
    m = _fit(epochs=1)
    head = 1280 * 256 + 256 + 256 + 1         # Dense(256) + Dense(1)
    base = sum(p.numel() for p in m.base_.parameters())
    assert m.n_parameters(trainable_only=True) == head
    assert m.n_parameters() == base + head + 2 * 1280   # + the feature standardisation
    assert base > 2_000_000


def test_deterministic_with_random_state():
    X, _ = _data(seed=5)
    a, b, c = _fit(random_state=3), _fit(random_state=3), _fit(random_state=4)
    assert a.base_fingerprint_ == b.base_fingerprint_
    assert np.array_equal(a.decision_function(X), b.decision_function(X))
    assert a.base_fingerprint_ != c.base_fingerprint_
    assert not np.allclose(a.decision_function(X), c.decision_function(X))


def test_precomputed_features_match_blocks():
    X, y = _data()
    m = TransferClassifier(arch=ARCH, epochs=5, batch_size=16).prepare_base(X)
    F = m.transform(X)
    assert F.shape == (len(X), A.ARCHS[ARCH].n_features) and F.dtype == np.float32
    assert F.std(axis=0).mean() > 1e-3        # calibrated BatchNorm: the random features live
    on_features = m.fit(F, y).decision_function(X)
    on_blocks = TransferClassifier(arch=ARCH, epochs=5, batch_size=16).fit(X, y).decision_function(X)
    assert np.allclose(on_features, on_blocks, atol=1e-5)
    assert np.allclose(m.decision_function(F), on_features, atol=1e-6)


def test_bad_inputs_and_params():
    X, y = _data(n=8)
    with pytest.raises(ValueError, match="unknown arch"):
        TransferClassifier(arch="alexnet").fit(X, y)
    with pytest.raises(ValueError, match="input_size"):
        TransferClassifier(arch="inception_v3", input_size=64).fit(X, y)
    with pytest.raises(ValueError, match="labels must be -1"):
        TransferClassifier(arch=ARCH, epochs=1).fit(X, (y > 0).astype(int))
    with pytest.raises(ValueError, match=r"\[n, h, w, 3\]"):
        TransferClassifier(arch=ARCH, epochs=1).fit(X[..., 0], y)
    with pytest.raises(ValueError, match="prepare_base"):
        TransferClassifier(arch=ARCH, epochs=1).fit(np.zeros((8, 1280)), y)
    m = TransferClassifier(arch=ARCH, epochs=1).fit(X, y)
    with pytest.raises(ValueError, match="1280"):
        m.decision_function(np.zeros((2, 26)))


def test_missing_weights_file_is_a_clear_error(tmp_path):
    X, y = _data(n=8)
    missing = tmp_path / "nope.pth"
    with pytest.raises(FileNotFoundError, match="nope.pth.*does not exist"):
        TransferClassifier(arch=ARCH, weights=str(missing), epochs=1).fit(X, y)


def test_wrong_or_broken_weights_file(tmp_path):
    X, y = _data(n=8)
    wrong = _state_dict_file(tmp_path / "r.pth", arch="resnet50")
    with pytest.raises(ValueError, match="not a mobilenet_v2 state_dict"):
        TransferClassifier(arch=ARCH, weights=str(wrong), epochs=1).fit(X, y)
    junk = tmp_path / "junk.pth"
    junk.write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="junk.pth.*not a readable"):
        TransferClassifier(arch=ARCH, weights=str(junk), epochs=1).fit(X, y)


def test_explicit_weights_file_is_loaded(tmp_path, caplog):
    path = _state_dict_file(tmp_path / "mine.pth")
    X, y = _data(n=8)
    with caplog.at_level(logging.WARNING, logger="learning.models.transfer"):
        m = TransferClassifier(arch=ARCH, weights=str(path), epochs=1).fit(X, y)
    assert "UNTRAINED" not in caplog.text
    assert m.base_pretrained_ is True and m.report_label() == f"{ARCH} (weights mine.pth)"
    ref = torch.load(path, weights_only=True)["features.0.0.weight"]
    assert torch.equal(m.base_.net.features[0][0].weight, ref)


def test_hub_cache_lookup_and_imagenet_label(tmp_path, monkeypatch):
    """A torchvision-named file in the hub cache is found; 'ImageNet' needs the name's hash."""
    cache = tmp_path / "torch_home" / "hub" / "checkpoints"
    cache.mkdir(parents=True)
    tmp = _state_dict_file(tmp_path / "w.pth")
    sha = hashlib.sha256(tmp.read_bytes()).hexdigest()
    name = f"{ARCH}-{sha[:8]}.pth"
    tmp.rename(cache / name)
    monkeypatch.setattr(W, "checkpoint_names", lambda arch: ["absent.pth", name])
    X, y = _data(n=8)
    m = TransferClassifier(arch=ARCH, epochs=1).fit(X, y)
    assert m.base_pretrained_ is True and m.report_label() == f"{ARCH} (ImageNet)"
    assert m.base_weights_ == str(cache / name)
    forged = f"{ARCH}-00000000.pth"             # a right name with the wrong content
    (cache / name).rename(cache / forged)
    monkeypatch.setattr(W, "checkpoint_names", lambda arch: [forged])
    m = TransferClassifier(arch=ARCH, epochs=1).fit(X, y)
    assert m.report_label() == f"{ARCH} (weights {forged})"


def test_checkpoint_names_are_torchvisions():
    names = W.checkpoint_names("vgg19")
    assert names[0].startswith("vgg19-") and names[0].endswith(".pth")
    assert len(W.checkpoint_names("resnet50")) >= 2     # V2 (default) and V1


def test_densenet_old_keys_are_renamed(tmp_path):
    t = torch.zeros(2)
    torch.save({"features.denseblock1.denselayer1.norm.1.weight": t, "features.conv0.weight": t},
               tmp_path / "d.pth")
    keys = set(W.read_state_dict(tmp_path / "d.pth"))
    assert keys == {"features.denseblock1.denselayer1.norm1.weight", "features.conv0.weight"}


@pytest.mark.parametrize("arch", list(A.ARCHS))
def test_every_arch_gives_pooled_features(arch):
    """All five bases build from torchvision and accept 32x32 blocks (inception: resized to 75)."""
    X, _ = _data(n=2)
    m = TransferClassifier(arch=arch, batch_size=2).prepare_base(X)
    F = m.transform(X)
    assert F.shape == (2, A.ARCHS[arch].n_features) and np.isfinite(F).all()
    assert m._images(X).shape[-1] == A.ARCHS[arch].min_size


def test_input_size_resizes():
    X, _ = _data(n=2, size=40)
    m = TransferClassifier(arch=ARCH, input_size=64)
    assert tuple(m._images(X).shape) == (2, 3, 64, 64)
    assert tuple(TransferClassifier(arch=ARCH)._images(X).shape) == (2, 3, 40, 40)


def test_clone_and_params():
    m = TransferClassifier(arch="resnet50", epochs=3, lr=0.01)
    c = clone(m)
    assert c.get_params() == m.get_params() and not hasattr(c, "head_")


@pytest.mark.parametrize("freeze", [True, False])
def test_save_load_roundtrip(tmp_path, freeze):
    X, _ = _data()
    m = _fit(epochs=2, freeze_base=freeze)
    m.save(tmp_path / "m")
    m.offset_ = 0.25                                  # a calibrated offset travels with the model
    m.save(tmp_path / "m")
    back = TransferClassifier.load(tmp_path / "m")
    assert back.offset_ == 0.25 and np.array_equal(back.predict(X), m.predict(X))
    assert np.array_equal(back.decision_function(X), m.decision_function(X))
    assert back.report_label() == m.report_label() and back.get_params() == m.get_params()


def test_load_refuses_a_different_base(tmp_path):
    m = _fit(epochs=1)
    m.save(tmp_path / "m")
    state = json.loads((tmp_path / "m" / S.STATE_FILE).read_text())
    state["params"]["random_state"] = 99     # rebuilds another random base
    (tmp_path / "m" / S.STATE_FILE).write_text(json.dumps(state))
    with pytest.raises(ValueError, match="differs from the one it was trained on"):
        TransferClassifier.load(tmp_path / "m")
    with pytest.raises(FileNotFoundError, match="transfer.json"):
        TransferClassifier.load(tmp_path / "empty")


def test_missing_torchvision_names_the_arches(monkeypatch):
    monkeypatch.setitem(sys.modules, "torchvision", None)
    with pytest.raises(ImportError, match="vgg19.*densenet201.*torchvision"):
        A.import_torchvision()


def test_torchvision_shim_only_when_needed():
    """In a fresh interpreter: schemas are defined iff torchvision's C extension did not load."""
    code = ("import learning.models.transfer_archs as T, torch; tv = T.import_torchvision();"
            "import torchvision.extension as E; m = tv.models.mobilenet_v2(weights=None);"
            "print(E._has_ops(), T._shim_lib is not None, hasattr(torch.ops.torchvision, 'nms'))")
    out = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    has_ops, shimmed, nms = out.stdout.split()
    assert nms == "True" and shimmed == str(has_ops == "False")
