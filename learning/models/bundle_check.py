"""What a model bundle must hold before anything uses it: its manifest's schema, the
estimator's fitted arrays, and the model file's hash.

Why: without these checks, crafted bundles load and then fail at the first verdict, or
never do and answer wrong. A manifest nested 100,000 deep raised RecursionError; `"input":
"Features"` (capitalised) skipped the feature-base check; a replaced fitted attribute
raised AttributeError mid-request; a NaN offset loaded and the model never converged; an
88 MB schema of nodes loaded in 1.1 GB, and an attribute no estimator of ours has was
kept as it came (the schema is now bounded before skops reads it, and attributes are known).
libsvm reads the support vectors through the counts it is given, so inconsistent arrays
would read out of bounds rather than raise. Everything here raises ValueError with the
file and the field, before the estimator answers anything.
"""
from __future__ import annotations

import functools
import hashlib
import io
import json
import math
import re
import zipfile
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from noisefeat.safeio import CAPS, open_input, read_input, read_named

from ..names import TRANSFER_INPUTS, TRANSFER_KINDS
from ..stoprule import OFFSET_LIMIT

#: the members of a model.skops, unpacked, all together (their headers' sizes, which bound
#: what zipfile inflates); the file itself is capped alike (`noisefeat.safeio.CAPS`)
MAX_MODEL_BYTES = CAPS["model"]
MAX_FEATURES = 1 << 24                        # a 4096x4096 raw block
MAX_SUPPORT_VECTORS = 1 << 22
#: a model.skops's schema.json (its object tree; the arrays are members of their own): the
#: X
#: and 6x of room while an 88 MB schema of nodes (1.1 GB to load) is refused unread
MAX_SCHEMA_BYTES = 1 << 20
MAX_SCHEMA_NODES = 5_000
_HEX64 = re.compile(r"^[0-9a-f]{64}$")


class _Strict(BaseModel):
    model_config = ConfigDict(strict=True, extra="allow")


class FeatureBaseInfo(_Strict):
    hash: str = Field(min_length=1, max_length=64)
    weights: str | None = None
    wavelet: str | None = None


class TrainingInfo(_Strict):
    """The parts of `training` that commands read (evaluate: the scenes not to test on)."""

    train_scenes: list[str] = []
    test_scenes: list[str] = []


class Manifest(_Strict):
    """manifest.json as `learning.models.bundle.save_model` writes it (unknown keys are kept)."""

    format: Literal["noisestop-model"]
    version: Literal[1]
    kind: str = Field(min_length=1, max_length=64)
    name: str | None = Field(default=None, min_length=1, max_length=64)
    input: Literal["features", "raw", "image"]
    feature_base: FeatureBaseInfo | None = None
    n_features: int | None = Field(default=None, ge=1, le=MAX_FEATURES)
    offset: float | None = Field(default=None, allow_inf_nan=False, ge=-OFFSET_LIMIT, le=OFFSET_LIMIT)
    quick: Literal["halves", "albedo", "direct", "none"] | None = None
    composition: str | None = Field(default=None, min_length=1, max_length=64)
    model_version: str | None = Field(default=None, min_length=1, max_length=64)
    model_sha256: str | None = None
    state_sha256: str | None = None
    params: dict[str, Any] = {}
    training: TrainingInfo = TrainingInfo()
    metrics: dict[str, Any] = {}
    versions: dict[str, Any] = {}


def read_manifest(path: Path) -> dict[str, Any]:
    """The manifest at `path` as a dict, validated against `Manifest`; ValueError otherwise."""
    data = read_input(path, "manifest")          # a regular file within its cap, else one line
    try:
        raw = json.loads(data)
    except RecursionError:
        raise ValueError(f"{path}: not a manifest (JSON nested too deeply)") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(raw, dict):
        raise ValueError(f"{path}: a manifest is a JSON object, got {type(raw).__name__}")
    if raw.get("format") != "noisestop-model" or raw.get("version") != 1:
        raise ValueError(f"{path.parent}: unsupported bundle format {raw.get('format')!r} "
                         f"version {raw.get('version')!r}")
    try:
        Manifest.model_validate(raw)
    except ValidationError as exc:
        first = exc.errors(include_url=False, include_input=False)[0]
        where = ".".join(str(p) for p in first["loc"]) or "manifest"
        raise ValueError(f"{path}: {where}: {first['msg']}") from None
    if raw["input"] == "raw" and raw.get("quick") not in (None, "none", "halves"):
        raise ValueError(f"{path}: unknown input mode quick={raw['quick']!r} for a raw model "
                         "(one of none, halves)")
    if raw["input"] == "image":
        if raw["kind"] not in TRANSFER_KINDS:
            raise ValueError(f"{path}: kind {raw['kind']!r} is not an image classifier "
                             f"(one of {', '.join(TRANSFER_KINDS)})")
        if raw.get("quick") not in TRANSFER_INPUTS:
            raise ValueError(f"{path}: unknown input mode quick={raw.get('quick')!r} for an image "
                             f"classifier (one of {', '.join(TRANSFER_INPUTS)})")
        for field in ("model_sha256", "state_sha256"):
            if not isinstance(raw.get(field), str) or not _HEX64.match(raw[field]):
                raise ValueError(f"{path}: an image classifier's manifest needs {field}, 64 lowercase "
                                 "hex digits")
    elif raw["kind"] in TRANSFER_KINDS:
        raise ValueError(f"{path}: kind {raw['kind']!r} is an image classifier, but input is {raw['input']!r}")
    if raw["input"] == "features" and raw.get("feature_base") is None:
        raise ValueError(f"{path}: a feature model must name the feature base it was trained on")
    if raw.get("model_sha256") is not None and not _HEX64.match(raw["model_sha256"]):
        raise ValueError(f"{path}: model_sha256 must be 64 lowercase hex digits")
    return raw


def file_sha256(path: Path, kind: str = "bundle") -> str:
    """SHA-256 of a file read in bounded chunks through `noisefeat.safeio` (a regular file
    within the cap of its `kind`: a link to a 3 GB sparse file is refused before hashing)."""
    h = hashlib.sha256()
    with open_input(path, kind) as f:
        for chunk in iter(lambda: read_named(f, path, kind, 1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


#: where our estimators lived before `learning` had sub-packages; a
#: bundle written then names the old module in its skops schema, and skops finds a class
#: by its module's name
MOVED_MODULES = {"learning.estimators": "learning.models.estimators"}


def model_bytes(path: Path, manifest: dict[str, Any]) -> bytes:
    """The model file's content, read once: with the manifest's hash if it has one, a zip
    whose members fit in memory (from its headers, before any is inflated), and with the
    module names of estimators that have moved since it was written replaced by their homes
    now, so that older bundles keep loading (the allow-list then judges the current names)."""
    data = read_input(path, "model")
    want = manifest.get("model_sha256")
    if want is not None and hashlib.sha256(data).hexdigest() != want:
        raise ValueError(f"{path}: content does not match the manifest's model_sha256 (changed or damaged)")
    try:
        zf = zipfile.ZipFile(io.BytesIO(data))
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        raise ValueError(f"{path}: unreadable skops file ({exc})") from None
    with zf:
        _check_unpacked(path, zf)
        try:
            size = zf.getinfo("schema.json").file_size
            if size > MAX_SCHEMA_BYTES:
                raise ValueError(f"{path}: its schema is {size} bytes, more than a model's ({MAX_SCHEMA_BYTES}); "
                                 "refused before reading it")
            schema = zf.read("schema.json")
            tree = json.loads(schema)
            moved = any(f'"{old}"'.encode() in schema for old in MOVED_MODULES)
            members = [(info, zf.read(info)) for info in zf.infolist()] if moved else []
        except (zipfile.BadZipFile, KeyError, OSError, RecursionError) as exc:
            raise ValueError(f"{path}: unreadable skops file ({type(exc).__name__}: {exc})") from None
        except ValueError as exc:
            raise ValueError(str(exc) if str(exc).startswith(f"{path}:")
                             else f"{path}: unreadable skops file ({type(exc).__name__}: {exc})") from None
    todo, nodes = [tree], 0
    while todo:                                   # iterative: a crafted schema may nest deep
        node = todo.pop()
        nodes += 1
        if nodes > MAX_SCHEMA_NODES:
            raise ValueError(f"{path}: its schema has more than {MAX_SCHEMA_NODES} nodes (a model's has about "
                             "800); refused before loading it")
        if isinstance(node, dict):
            if node.get("__module__") in MOVED_MODULES:
                node["__module__"] = MOVED_MODULES[node["__module__"]]
            todo.extend(node.values())
        elif isinstance(node, list):
            todo.extend(node)
    if not moved:
        return data
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as zf:
        for info, raw in members:
            zf.writestr(info, json.dumps(tree).encode() if info.filename == "schema.json" else raw)
    return out.getvalue()


def _check_unpacked(path: Path, zf: zipfile.ZipFile) -> None:
    """The members' unpacked sizes from their headers, within `MAX_MODEL_BYTES`: zipfile
    never inflates a member past its header's size (it stops there and checks the CRC),
    so this bounds what reading the members, here or in skops, can cost."""
    total = sum(i.file_size for i in zf.infolist())
    if total > MAX_MODEL_BYTES:
        raise ValueError(f"{path}: unpacks to {total} bytes, more than a model may take ({MAX_MODEL_BYTES}); "
                         "refused before inflating it")


# ----------------------------------------------------------------------------- estimator


def _array(owner: str, name: str, value: Any, dtype: str, shape: tuple[int | None, ...]) -> np.ndarray:
    """`value` must be an ndarray of `dtype` kind/size and `shape` (None: any), finite if float."""
    where = f"{owner}.{name}"
    if type(value) is not np.ndarray:
        raise ValueError(f"{where} must be an array, got {type(value).__name__}")
    if value.dtype != np.dtype(dtype):
        raise ValueError(f"{where} must be {dtype}, got {value.dtype}")
    if value.ndim != len(shape) or any(s is not None and s != v for s, v in zip(shape, value.shape)):
        want = "x".join("n" if s is None else str(s) for s in shape) or "scalar"
        raise ValueError(f"{where} must have shape {want}, got {list(value.shape)}")
    if value.dtype.kind == "f" and not np.isfinite(value).all():
        raise ValueError(f"{where} holds NaN or Inf")
    return value


def _number(where: str, value: Any, low: float, high: float, integer: bool = False) -> float:
    kinds = (int, np.integer) if integer else (int, float, np.integer, np.floating)
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, kinds) or not math.isfinite(float(value)) \
            or not low <= value <= high:
        raise ValueError(f"{where} must be a {'whole ' if integer else ''}number in [{low:g}, {high:g}], got {value!r}")
    return float(value)


#: the fitted attributes (beyond the constructor's parameters) each object of a model may
#: hold; anything else in a bundle was not written by noisestop's training and is refused
#: (`offset`: bundles from before offset_ was fitted; `feature_names_in_`: sklearn's own)
ESTIMATOR_FITTED = frozenset({"n_features_in_", "classes_", "offset_", "range_", "scaler_", "svc_", "constant_",
                              "offset", "feature_names_in_"})
SCALER_FITTED = frozenset({"mean_", "var_", "scale_", "n_samples_seen_", "n_features_in_", "feature_names_in_"})


@functools.cache
def _svc_fitted() -> frozenset[str]:
    """What this sklearn's fitted SVC holds (its private arrays move between releases)."""
    from sklearn.svm import SVC

    return frozenset(vars(SVC().fit(np.array([[0.0], [1.0]]), np.array([-1, 1])))) | {"feature_names_in_"}


def _known_attributes(owner: str, obj: Any, fitted: frozenset[str]) -> None:
    """ValueError naming the first attribute of `obj` that is neither a parameter of its
    class nor one of its `fitted` attributes."""
    unknown = sorted(set(vars(obj)) - set(obj.get_params(deep=False)) - fitted)
    if unknown:
        raise ValueError(f"{owner} has unknown attribute {unknown[0]!r} (not one noisestop's training writes)")


def check_estimator(est: Any, expected_features: int | None = None) -> None:
    """Every fitted attribute an `RBFSVM` reads when it answers, by exact type, dtype and shape."""
    from sklearn.preprocessing import StandardScaler
    from sklearn.svm import SVC

    from .estimators import DSVM, SVM, RBFSVM

    if type(est) not in (RBFSVM, DSVM, SVM):
        raise ValueError(f"holds a {type(est).__name__}, not a noisestop SVM")
    _known_attributes("estimator", est, ESTIMATOR_FITTED)
    d = int(_number("n_features_in_", getattr(est, "n_features_in_", None), 1, MAX_FEATURES, integer=True))
    if expected_features is not None and d != expected_features:
        raise ValueError(f"n_features_in_ is {d}, the manifest says {expected_features}")
    classes = _array("estimator", "classes_", getattr(est, "classes_", None), "int64", (2,))
    if classes.tolist() != [-1, 1]:
        raise ValueError(f"classes_ must be [-1, 1], got {classes.tolist()}")
    _number("offset_", getattr(est, "offset_", None), -OFFSET_LIMIT, OFFSET_LIMIT)
    rng = getattr(est, "range_", None)
    if rng is not None:
        _array("estimator", "range_", rng, "float64", (2, d))
        if (rng[0] > rng[1]).any():
            raise ValueError("range_ has a lower bound above its upper bound")
    scaler = getattr(est, "scaler_", None)
    if scaler is not None:
        if type(scaler) is not StandardScaler:
            raise ValueError(f"scaler_ must be a StandardScaler, got {type(scaler).__name__}")
        _known_attributes("scaler_", scaler, SCALER_FITTED)
        for flag in ("with_mean", "with_std"):
            if not isinstance(getattr(scaler, flag, None), bool):
                raise ValueError(f"scaler_.{flag} must be true or false")
        if scaler.with_mean:
            _array("scaler_", "mean_", getattr(scaler, "mean_", None), "float64", (d,))
        if scaler.with_std and (_array("scaler_", "scale_", getattr(scaler, "scale_", None), "float64", (d,))
                                <= 0).any():
            raise ValueError("scaler_.scale_ must be positive")
        if getattr(scaler, "n_features_in_", d) != d:
            raise ValueError(f"scaler_.n_features_in_ is {scaler.n_features_in_}, the model takes {d}")
    elif getattr(est, "standardize", False) is True and "scaler_" not in vars(est):
        raise ValueError("scaler_ is missing")
    svc = getattr(est, "svc_", None)
    constant = getattr(est, "constant_", None)
    if svc is None:
        if constant not in (-1, 1) or isinstance(constant, bool):
            raise ValueError(f"a model without svc_ must answer a constant -1 or 1, got constant_ = {constant!r}")
        return
    if constant is not None:
        raise ValueError("constant_ must be None when svc_ is fitted")
    if type(svc) is not SVC:
        raise ValueError(f"svc_ must be an sklearn SVC, got {type(svc).__name__}")
    _known_attributes("svc_", svc, _svc_fitted())
    _check_svc(svc, d)


def _check_svc(svc: Any, d: int) -> None:
    """The arrays and settings libsvm's decision function reads (sklearn.svm._base)."""
    if svc.kernel != "rbf" or svc.__dict__.get("_sparse") is not False:
        raise ValueError(f"svc_ must be a dense RBF SVC, got kernel {svc.kernel!r}")
    if getattr(svc, "decision_function_shape", None) not in ("ovr", "ovo"):
        raise ValueError("svc_.decision_function_shape must be 'ovr' or 'ovo'")
    sv = _array("svc_", "support_vectors_", getattr(svc, "support_vectors_", None), "float64", (None, d))
    n_sv = sv.shape[0]
    if not 1 <= n_sv <= MAX_SUPPORT_VECTORS or not sv.flags.c_contiguous:
        raise ValueError(f"svc_.support_vectors_ must hold 1..{MAX_SUPPORT_VECTORS} C-ordered rows, got {n_sv}")
    support = _array("svc_", "support_", getattr(svc, "support_", None), "int32", (n_sv,))
    if (support < 0).any():
        raise ValueError("svc_.support_ holds negative indices")
    counts = _array("svc_", "_n_support", getattr(svc, "_n_support", None), "int32", (2,))
    if (counts < 0).any() or int(counts.sum()) != n_sv:
        raise ValueError(f"svc_._n_support {counts.tolist()} does not add up to {n_sv} support vectors")
    for name in ("dual_coef_", "_dual_coef_"):
        _array("svc_", name, getattr(svc, name, None), "float64", (1, n_sv))
    for name in ("intercept_", "_intercept_"):
        _array("svc_", name, getattr(svc, name, None), "float64", (1,))
    for name in ("_probA", "_probB"):
        _array("svc_", name, getattr(svc, name, None), "float64", (None,))
    classes = _array("svc_", "classes_", getattr(svc, "classes_", None), "int64", (2,))
    if classes.tolist() != [-1, 1]:
        raise ValueError(f"svc_.classes_ must be [-1, 1], got {classes.tolist()}")
    _number("svc_._gamma", getattr(svc, "_gamma", None), 1e-300, 1e300)
    _number("svc_.degree", getattr(svc, "degree", None), 0, 100, integer=True)
    _number("svc_.coef0", getattr(svc, "coef0", None), -1e300, 1e300)
    _number("svc_.cache_size", getattr(svc, "cache_size", None), 1e-3, 1e6)
    _number("svc_.n_features_in_", getattr(svc, "n_features_in_", None), d, d, integer=True)
    shape_fit = getattr(svc, "shape_fit_", None)
    if not (isinstance(shape_fit, tuple) and len(shape_fit) == 2 and shape_fit[1] == d):
        raise ValueError(f"svc_.shape_fit_ must be (n, {d}), got {shape_fit!r}")
    if getattr(svc, "fit_status_", None) != 0 or not isinstance(getattr(svc, "break_ties", None), bool):
        raise ValueError("svc_ is not a successfully fitted SVC (fit_status_ / break_ties)")
    if getattr(svc, "_impl", "c_svc") != "c_svc":
        raise ValueError("svc_ must be a C-SVC")


def load_skops(data: bytes, allowed: list[str], path: Path) -> Any:
    """The object a skops file holds, built only from `allowed` types (never `trusted=True`):
    ValueError naming `path` on a malformed file or any other type."""
    import skops.io as sio

    try:
        untrusted = sio.get_untrusted_types(data=data)
    except Exception as exc:     # skops raises many kinds of errors on a malformed file
        raise ValueError(f"{path}: unreadable skops file ({type(exc).__name__}: {exc})") from None
    unknown = [t for t in untrusted if t not in allowed]
    if unknown:
        raise ValueError(f"{path}: refuses to load unknown types {unknown}")
    try:
        return sio.loads(data, trusted=untrusted)
    except Exception as exc:     # e.g. a spoofed type name: AttributeError inside skops
        raise ValueError(f"{path}: unreadable skops file ({type(exc).__name__}: {exc})") from None
