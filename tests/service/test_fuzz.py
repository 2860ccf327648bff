"""Bounded fuzzing: the readers of untrusted bytes either answer or refuse cleanly.

Hypothesis drives the binary tensor decoder (request header + tail), the manifest reader
and the checkpoint reader with malformed, mutated and forged input. The only outcomes
allowed are a result or the documented error (ApiError 4xx, ValueError); anything else
(KeyError, IndexError, MemoryError, an ApiError 5xx...) fails the test. Example counts are
fixed and small so that the suite stays bounded; the counts are reported in BENCHMARKS.md.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from learning.data.accumulator import UnitAccumulator
from learning.models.bundle_check import read_manifest
from learning.data.npz import read_npz, savez_bytes
from renderer.live.checkpoint import load_checkpoint, save_checkpoint
from renderer.live.progress import LoopState, Progress, RunSettings
from service.limits import Limits
from service.oip import DATATYPES, ApiError, decode_tensors, parse_request, split_body

FUZZ = settings(max_examples=150, deadline=None, database=None,
                suppress_health_check=list(HealthCheck))
LIMITS = Limits(max_body_bytes=1 << 20, max_batch=64, max_block_side=64, max_pixels=4096)

# --- binary tensor decoder -------------------------------------------------------------------

dims = st.one_of(st.integers(0, 4), st.integers(0, 2**31 + 5), st.sampled_from([2**40, -1, 1.5, "2", None]))
shapes = st.one_of(st.lists(dims, max_size=6), st.just("x"), st.none())
inputs = st.fixed_dictionaries(
    {"name": st.sampled_from(["blocks", "quick", "features", "even", ""]),
     "shape": shapes,
     "datatype": st.sampled_from([*DATATYPES, "BYTES", "fp32", 7])},
    optional={"parameters": st.one_of(
        st.fixed_dictionaries({"binary_data_size": st.one_of(st.integers(-5, 400), st.booleans(),
                                                             st.just(10**400), st.text(max_size=3))}),
        st.none(), st.just([])),
        "data": st.one_of(st.lists(st.one_of(st.floats(allow_nan=True), st.integers(), st.booleans(),
                                             st.text(max_size=2), st.lists(st.integers(), max_size=3)),
                                   max_size=12), st.just("abc"), st.none())})


def decode(body: bytes, header_length: int | None) -> dict[str, np.ndarray]:
    """What the infer route does with a body before the model runs."""
    head, tail = split_body(body, header_length)
    req = parse_request(bytes(head))
    LIMITS.check_shapes(req.inputs)
    return decode_tensors(req, tail, LIMITS.max_batch)


@FUZZ
@given(header=st.fixed_dictionaries({"inputs": st.lists(inputs, max_size=3)},
                                    optional={"parameters": st.dictionaries(st.text(max_size=5), st.integers())}),
       tail=st.binary(max_size=600), cut=st.integers(-3, 3))
def test_binary_tensor_decoder_answers_or_refuses(header, tail, cut):
    head = json.dumps(header).replace("Infinity", "1e999").encode()
    body = head + tail
    length = max(0, len(head) + cut) if cut else len(head)
    try:
        arrays = decode(body, length)
    except ApiError as exc:
        assert 400 <= exc.status < 500 and exc.message
        return
    for name, arr in arrays.items():
        assert isinstance(arr, np.ndarray) and arr.dtype in DATATYPES.values()


@FUZZ
@given(raw=st.binary(max_size=300))
def test_json_request_parser_refuses_garbage(raw):
    try:
        decode(raw, None)
    except ApiError as exc:
        assert 400 <= exc.status < 500


# --- the memory estimate of a JSON body, and keys given twice ---------------------------------

ESTIMATE = settings(max_examples=20, deadline=None, database=None, suppress_health_check=list(HealthCheck))
ROOMY = Limits(max_body_bytes=1 << 30, max_batch=1 << 20, max_block_side=1 << 20, max_pixels=1 << 30)


@ESTIMATE
@given(depth=st.integers(0, 20), kind=st.sampled_from(["small int", "int", "float", "short float", "object"]),
       count=st.integers(1000, 6000), spaces=st.integers(0, 3))
def test_json_cost_estimate_covers_what_decoding_takes(depth, kind, count, spaces):
    """The estimate made from a byte count before parsing is at least the memory parsing,
    validating and decoding really take (tracemalloc's peak: Python objects and numpy),
    whatever the shape: nesting, number kinds, objects in place of numbers, whitespace."""
    import tracemalloc

    from service.memory_cost import json_cost
    value = {"small int": b"7", "int": b"123457", "float": b"0.123456789", "short float": b"1e5",
             "object": b'{"a":1}'}[kind]
    sep = b"," + b" " * spaces
    unit = b"[" * depth + value + b"]" * depth
    shape = [count] + [1] * min(depth, 7)
    body = (b'{"inputs": [{"name": "features", "datatype": "FP32", "shape": %s, "data": [' % json.dumps(shape).encode()
            + sep.join([unit] * count) + b"]}]}")
    tracemalloc.start()
    try:
        req = parse_request(body)
        ROOMY.check_shapes(req.inputs)
        decode_tensors(req, b"", ROOMY.max_batch)
    except ApiError as exc:
        assert exc.status == 400
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    assert json_cost(body) + (64 << 10) >= peak, (kind, depth, count, json_cost(body), peak)


json_keys = st.text(alphabet="abce:x", min_size=1, max_size=4)


@FUZZ
@given(obj=st.recursive(st.dictionaries(json_keys, st.integers(), max_size=3),
                        lambda children: st.dictionaries(json_keys, children, max_size=3), max_leaves=12),
       twice=st.booleans(), where=st.integers(0, 100))
def test_a_key_given_twice_is_always_found(obj, twice, where):
    """Any object, at any depth, with a key repeated: 400 naming the key; without one, the
    duplicate check never fires (colons in keys and strings included)."""
    text = json.dumps({"parameters": obj, "inputs": [{"name": "features", "shape": [1, 26], "datatype": "FP32",
                                                      "data": [0.5] * 26}]})
    if twice:
        opens = [i for i, ch in enumerate(text) if ch == "{"]
        at = opens[where % len(opens)] + 1
        text = text[:at] + '"k:" : 1, "k:": 2' + ("," if text[at] != "}" else "") + text[at:]
    try:
        parse_request(text.encode())
    except ApiError as exc:
        assert exc.status == 400
        assert ("appears twice" in exc.message) == twice, (text, exc.message)
        return
    assert not twice, text


# --- manifest reader --------------------------------------------------------------------------

json_values = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=8)),
    lambda children: st.one_of(st.lists(children, max_size=4), st.dictionaries(st.text(max_size=8), children,
                                                                               max_size=4)),
    max_leaves=20)
GOOD_MANIFEST = {"format": "noisestop-model", "version": 1, "kind": "dsvm", "name": "m", "input": "features",
                 "feature_base": {"hash": "abc"}, "n_features": 26, "offset": 0.0}


@FUZZ
@given(changes=st.dictionaries(st.sampled_from([*GOOD_MANIFEST, "quick", "composition", "model_sha256",
                                                "training", "model_version"]), json_values, max_size=4),
       raw=st.one_of(st.none(), st.binary(max_size=200)))
def test_manifest_reader_answers_or_refuses(tmp_path_factory, changes, raw):
    path = tmp_path_factory.mktemp("m") / "manifest.json"
    path.write_bytes(raw if raw is not None else json.dumps({**GOOD_MANIFEST, **changes}).encode())
    try:
        manifest = read_manifest(path)
    except ValueError as exc:
        assert str(path) in str(exc) or "format" in str(exc)
        return
    assert manifest["input"] in ("features", "raw") and manifest["format"] == "noisestop-model"


# --- checkpoint reader ------------------------------------------------------------------------

GRID, BLOCK, FRAME, SIZES = (2, 2), (8, 8), (16, 16), [4, 4, 4, 4]
SETTINGS = RunSettings(scene="fuzz", resolution=FRAME, grid=GRID, block=BLOCK, tile=BLOCK, exposure=0.0, step=4,
                       min_spp=4, max_spp=16, decide_skip=0.0, decide_growth=0.0, seed=0, quick_spp=0, quick="none",
                       criterion={"name": "fuzz"}, variant="scalar_rgb", defines={}, tau=0.02)


def _valid_checkpoint(path: Path) -> None:
    """Two passes of a 2x2 grid, block 0 stopped at the second: what the loop would save."""
    acc = UnitAccumulator(GRID, BLOCK)
    rng = np.random.default_rng(0)
    active = np.ones(4, bool)
    history, stop_spp, rendered = [], np.zeros(4, np.int64), []
    for p in range(2):
        ids = np.flatnonzero(active).tolist()
        acc.add_many(ids, rng.random((len(ids), *BLOCK, 3)).astype(np.float32), SIZES[p])
        row = np.zeros(4, np.int8)
        row[ids] = -1
        if p == 1:
            row[0], active[0], stop_spp[0] = 1, False, 8
        history.append(row)
        rendered.append(len(ids))
    loop = LoopState(acc=acc, active=active, stop_spp=stop_spp, history=np.stack(history),
                     history_spp=np.array([4, 8]), history_unit_spp=np.array([[4] * 4, [8] * 4]),
                     rendered=np.array(rendered), evidence=np.tile([[2.4, 8.0]], (4, 1)),   # weights: the 8 spp decided
                     next_spp=np.full(4, 8))
    save_checkpoint(path, Progress(loop, done=False, counters={"decide_calls": 2}, timers={"wall_s": 0.5}), SETTINGS)


def _load(path: Path) -> Progress:
    return load_checkpoint(path, SETTINGS, pass_spp=SIZES, grid=GRID, unit_shape=BLOCK, frame=FRAME)


@pytest.fixture(scope="module")
def valid_checkpoint(tmp_path_factory) -> bytes:
    path = tmp_path_factory.mktemp("ck") / "checkpoint.npz"
    _valid_checkpoint(path)
    state = _load(path)                                  # the reader accepts what the writer wrote
    assert state.rows == 2 and state.loop.stop_spp.tolist() == [8, 0, 0, 0]
    return path.read_bytes()


@FUZZ
@given(data=st.data())
def test_checkpoint_reader_refuses_damaged_bytes(tmp_path_factory, valid_checkpoint, data):
    raw = bytearray(valid_checkpoint)
    for _ in range(data.draw(st.integers(1, 4))):
        kind = data.draw(st.sampled_from(["flip", "truncate", "insert", "zero"]))
        at = data.draw(st.integers(0, max(0, len(raw) - 1)))
        if kind == "flip" and raw:
            raw[at] ^= data.draw(st.integers(1, 255))
        elif kind == "truncate":
            del raw[at:]
        elif kind == "insert":
            raw[at:at] = data.draw(st.binary(min_size=1, max_size=8))
        elif kind == "zero":
            raw[at:at + 16] = bytes(len(raw[at:at + 16]))
    path = tmp_path_factory.mktemp("ck") / "checkpoint.npz"
    path.write_bytes(bytes(raw))
    try:
        state = _load(path)
    except ValueError as exc:
        assert "checkpoint.npz" in str(exc)
        return
    assert bytes(raw) == valid_checkpoint or state.rows == 2   # a no-op mutation


@FUZZ
@given(data=st.data())
def test_checkpoint_reader_refuses_forged_states(tmp_path_factory, valid_checkpoint, data):
    """Arrays replaced by others of any dtype and shape, the digest recomputed (a forger's
    checkpoint): refused unless the state is one the loop could have saved."""
    src = tmp_path_factory.mktemp("ck") / "src.npz"
    src.write_bytes(valid_checkpoint)
    arrays = read_npz(src)
    arrays.pop("sha256")
    key = data.draw(st.sampled_from(sorted(arrays)))
    dtype = data.draw(st.sampled_from(["int64", "int8", "float64", "float32", "bool", "<U4"]))
    shape = tuple(data.draw(st.lists(st.integers(0, 5), max_size=3)))
    fill = data.draw(st.sampled_from([0, 1, -1, 10**6, np.nan]))
    try:
        arrays[key] = np.full(shape, fill, dtype=dtype)
    except (ValueError, OverflowError, TypeError):
        arrays[key] = np.zeros(shape, dtype=dtype)
    path = tmp_path_factory.mktemp("ck") / "checkpoint.npz"
    path.write_bytes(savez_bytes(arrays, with_digest=True))
    try:
        state = _load(path)
    except ValueError:
        return
    assert 0 <= state.rows <= len(SIZES)
