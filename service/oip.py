"""Open Inference Protocol v2: its messages as pydantic models, and its tensor wire format.

The models are what the OpenAPI document shows and what a request header is validated
against (strictly: a number written as a string is an error, not a guess). Tensor data is
not validated element by element by pydantic: a 16-block request holds ~1.5 M numbers, so
`decode_tensors` turns it into numpy arrays and checks shape, datatype and length there.
Binary tensor extension (REFERENCES.md): the body is a JSON header of
`Inference-Header-Content-Length` bytes followed by raw little-endian row-major tensors in
input order, each announced by `parameters.binary_data_size`; the bytes go through the codec
the client uses too (`renderer.client.oip_codec`).
"""
from __future__ import annotations

import math
from typing import Annotated, Any

import numpy as np
import pydantic_core
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, PlainValidator, ValidationError

from renderer.client import oip_codec
from service.jsonguard import max_depth
from renderer.client.oip_codec import BINARY_EXTENSION, DATATYPES, HEADER_LENGTH, WireError, join_body, read_tensor, tensor_bytes

__all__ = ["BINARY_EXTENSION", "DATATYPES", "HEADER_LENGTH", "ApiError", "decode_tensors", "encode_response",
           "parse_request", "split_body"]
Datatype = Annotated[str, Field(description="OIP tensor datatype, e.g. FP32, INT8",
                                json_schema_extra={"enum": sorted(DATATYPES)})]


class ApiError(Exception):
    """A client-side problem, answered with `status` and {"error": message}."""

    def __init__(self, status: int, message: str, headers: dict[str, str] | None = None) -> None:
        super().__init__(message)
        self.status = status
        self.message = message
        self.headers = headers


class _Message(BaseModel):
    model_config = ConfigDict(strict=True)


class ErrorResponse(_Message):
    error: str


class LiveResponse(_Message):
    live: bool


class ReadyResponse(_Message):
    ready: bool


class ModelReadyResponse(_Message):
    name: str
    ready: bool


class ServerMetadata(_Message):
    name: str
    version: str
    extensions: list[str]


class TensorMetadata(_Message):
    name: str
    datatype: str
    shape: list[int]


class ModelMetadata(_Message):
    name: str
    versions: list[str]
    platform: str
    inputs: list[TensorMetadata]
    outputs: list[TensorMetadata]
    parameters: dict[str, Any] | None = None


class RepositoryModel(_Message):
    name: str
    version: str
    state: str
    reason: str = ""


Parameters = dict[str, Any]


def _integral(value: Any) -> Any:
    """JSON Schema's integer includes 2.0; strict validation would refuse it."""
    return int(value) if isinstance(value, float) and value.is_integer() else value


#: a tensor dimension; numpy's own limits (64 axes, sizes below 2**63) turned into a 400
MAX_DIM = 2**31 - 1
MAX_RANK = 8
#: the deepest JSON an infer request needs: request, inputs, input, data nested per axis
MAX_JSON_DEPTH = 3 + MAX_RANK
Dim = Annotated[int, BeforeValidator(_integral), Field(ge=0, le=MAX_DIM)]


def _list_as_is(value: Any) -> list[Any]:
    """Tensor data is kept as parsed (validating list[Any] copies it: 8 bytes a value);
    `decode_tensors` checks its contents."""
    if not isinstance(value, list):
        raise ValueError("data must be a list")
    return value


TensorData = Annotated[list[Any], PlainValidator(_list_as_is, json_schema_input_type=list[Any])]


class RequestInput(_Message):
    name: str
    shape: list[Dim] = Field(max_length=MAX_RANK)
    datatype: Datatype
    parameters: Parameters | None = None
    data: TensorData | None = Field(
        default=None, description="row-major values, flat or nested; omitted for binary data")


class RequestOutput(_Message):
    name: str
    parameters: Parameters | None = None


class InferenceRequest(_Message):
    id: str | None = None
    parameters: Parameters | None = None
    inputs: list[RequestInput] = Field(min_length=1)
    outputs: list[RequestOutput] | None = None


class ResponseOutput(_Message):
    name: str
    shape: list[int]
    datatype: str
    parameters: Parameters | None = None
    data: list[Any] | None = None


class InferenceResponse(_Message):
    model_name: str
    model_version: str | None = None
    id: str | None = None
    parameters: Parameters | None = None
    outputs: list[ResponseOutput]


def split_body(body: bytes | memoryview, header_length: int | None) -> tuple[bytes | memoryview, bytes | memoryview]:
    """(JSON header, binary tail) of a request body (slices of a memoryview: no copy)."""
    try:
        return oip_codec.split_body(body, header_length)
    except WireError as exc:
        raise ApiError(400, str(exc)) from None


def parse_request(header: bytes) -> InferenceRequest:
    """Validate the JSON header of an infer request; every problem is a 400, a key twice in
    one JSON object included (parsers keep the last: `exposure: 1e30, exposure: 0` would
    be served at 0)."""
    depth = max_depth(header)
    if depth > MAX_JSON_DEPTH:    # refused before anything is built (service.jsonguard)
        raise ApiError(400, f"invalid inference request: JSON nested {depth} deep; a request needs at most "
                            f"{MAX_JSON_DEPTH} (an input's data flat, or nested once per axis of its shape)")
    try:  # pydantic-core's parser: ~6x json.loads on number arrays; bounded nesting depth
        obj = pydantic_core.from_json(header, allow_inf_nan=True)
    except ValueError as exc:
        raise ApiError(400, f"invalid JSON: {exc}") from None
    if _colons(obj) != header.count(b":"):    # fewer entries than colons: maybe a key twice
        del obj
        obj = _parse_unique_keys(header)
    try:
        return InferenceRequest.model_validate(obj)
    except ValidationError as exc:
        raise ApiError(400, "invalid inference request: " + _summarise(exc)) from None


def _colons(obj: Any) -> int:
    """The colons the JSON text of `obj` holds if no object has a key twice: one per object
    entry, plus those inside strings. Tensor `data` lists are not walked (numbers hold no
    colon; a `data` with objects or strings in it then counts short, and is checked by
    `_parse_unique_keys`, as is any text whose count differs)."""
    count = 0
    stack = [obj]
    while stack:
        x = stack.pop()
        if isinstance(x, dict):
            count += len(x)
            for k, v in x.items():
                count += k.count(":")
                if not (k == "data" and isinstance(v, list)):
                    stack.append(v)
        elif isinstance(x, list):
            stack.extend(x)
        elif isinstance(x, str):
            count += x.count(":")
    return count


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out = dict(pairs)
    if len(out) != len(pairs):
        seen: set[str] = set()
        twice = next(k for k, _ in pairs if k in seen or seen.add(k))
        raise ApiError(400, f"invalid JSON: key {twice[:80]!r} appears twice in one object")
    return out


def _parse_unique_keys(header: bytes) -> Any:
    """The JSON text parsed by the standard library, refusing a key twice in one object
    (the slow path, taken only when the colon count says a key may be repeated)."""
    import json
    try:
        return json.loads(header, object_pairs_hook=_no_duplicates)
    except (ValueError, RecursionError) as exc:
        raise ApiError(400, f"invalid JSON: {str(exc)[:200]}") from None


def may_hold_bools(header: bytes) -> bool:
    """False when the JSON text has no true/false literal anywhere (then no scan is needed)."""
    return b"true" in header or b"false" in header


def _summarise(exc: ValidationError, limit: int = 3) -> str:
    errs = exc.errors(include_url=False, include_input=False)
    parts = [f"{'.'.join(str(p) for p in e['loc']) or 'body'}: {e['msg']}" for e in errs[:limit]]
    more = f" (and {len(errs) - limit} more)" if len(errs) > limit else ""
    return "; ".join(parts) + more


def param(params: Parameters | None, key: str, kinds: type | tuple[type, ...], default: Any) -> Any:
    """A typed request parameter (a JSON true is not accepted where a number is expected)."""
    kinds = kinds if isinstance(kinds, tuple) else (kinds,)
    value = (params or {}).get(key, default)
    if value is default:
        return value
    if not isinstance(value, kinds) or (isinstance(value, bool) and bool not in kinds):
        names = " or ".join(k.__name__ for k in kinds)
        raise ApiError(400, f"parameter {key!r} must be a {names}, got {value!r}")
    return value


def number_param(params: Parameters | None, key: str, default: float | None, low: float,
                 high: float) -> float | None:
    """A request parameter that must be a number in [low, high] (JSON true is not a number).

    Compared before any conversion to float: a 400-digit integer is out of range, not an
    OverflowError, and NaN or Inf is never in range."""
    value = (params or {}).get(key)
    if value is None:               # absent or null: the default
        return default
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ApiError(400, f"parameter {key!r} must be a number in [{low:g}, {high:g}], got {str(value)[:80]!r}")
    if not low <= value <= high:   # int vs float comparison is exact in Python; NaN fails it
        shown = value if isinstance(value, float) or abs(value) < 10**30 else f"a {len(str(abs(value)))}-digit number"
        raise ApiError(400, f"parameter {key!r} must be a number in [{low:g}, {high:g}], got {shown}")
    return float(value)


def decode_tensors(req: InferenceRequest, binary: bytes | memoryview, max_batch: int,
                   scan_bools: bool = True) -> dict[str, np.ndarray]:
    """Input tensors by name, shaped as declared; checks the batch limit before any copy.

    Binary tensors are numpy views of `binary` (no copy) when it is writable and they are
    aligned (service.body.read_body places them so); otherwise copies.

    `scan_bools=False` skips looking for JSON true/false among numbers (callers that know
    the JSON text holds no such literal: `may_hold_bools`)."""
    names = [t.name for t in req.inputs]
    if len(set(names)) != len(names):
        raise ApiError(400, f"input names must be unique, got {names}")
    for t in req.inputs:       # what the request says is checked before what it weighs
        if t.datatype not in DATATYPES:
            raise ApiError(400, f"input {t.name!r}: unsupported datatype {t.datatype!r}")
    check_batch(req, max_batch)
    arrays, offset = {}, 0
    for t in req.inputs:
        dtype = DATATYPES[t.datatype]
        count = math.prod(t.shape)
        size = param(t.parameters, "binary_data_size", int, None)
        if size is not None:
            if t.data is not None:
                raise ApiError(400, f"input {t.name!r} has both JSON data and binary_data_size")
            try:
                arrays[t.name] = read_tensor(binary, t.datatype, t.shape, size, offset, f"input {t.name!r}")
            except WireError as exc:
                raise ApiError(400, str(exc)) from None
            offset += size
            continue
        if t.data is None:
            raise ApiError(400, f"input {t.name!r} has neither data nor binary_data_size")
        flat = _json_values(t.name, t.data, dtype, scan_bools)
        if flat.size != count:
            raise ApiError(400, f"input {t.name!r}: {flat.size} values for shape {t.shape} "
                                f"({count} expected)")
        arrays[t.name] = flat.reshape(t.shape)
    if offset != len(binary):
        raise ApiError(400, f"{len(binary) - offset} bytes of binary data belong to no input")
    return arrays


def check_batch(req: InferenceRequest, max_batch: int) -> None:
    """413 for an input whose first axis holds more than `max_batch` items."""
    for t in req.inputs:
        if t.shape and t.shape[0] > max_batch:
            raise ApiError(413, f"input {t.name!r} holds {t.shape[0]} items; the limit is "
                                f"{max_batch} per request")


def _json_values(name: str, data: list[Any] | np.ndarray, dtype: np.dtype, scan_bools: bool = True) -> np.ndarray:
    try:
        values = np.asarray(data)
    except (ValueError, TypeError, RecursionError):
        raise ApiError(400, f"input {name!r}: data is ragged or not all numbers") from None
    if values.size:
        if dtype.kind == "b":
            if values.dtype.kind != "b":
                raise ApiError(400, f"input {name!r}: data must be true/false for BOOL")
        elif values.dtype.kind not in "iuf":
            got = "true/false" if values.dtype.kind == "b" else f"{values.dtype.kind!r}"
            raise ApiError(400, f"input {name!r}: data must be numbers for {dtype.name}, got {got} values")
        elif scan_bools and isinstance(data, list) and _holds_bool(data):   # numpy would read true as 1
            raise ApiError(400, f"input {name!r}: data must be numbers for {dtype.name}, got true/false "
                                "among them")
    if values.size and dtype.kind in "iu" and values.dtype.kind == "f":
        raise ApiError(400, f"input {name!r}: integer datatype but fractional data")
    with np.errstate(over="ignore"):  # 1e300 as FP32 is +Inf, which the display rule reads
        return values.astype(dtype, copy=False).reshape(-1)


def _holds_bool(data: list[Any]) -> bool:
    """Whether nested lists hold a JSON true/false, which numpy would silently read as 1/0."""
    stack = [data]
    while stack:
        items = stack.pop()
        if items and isinstance(items[0], list):
            stack.extend(items)
        elif bool in set(map(type, items)):
            return True
    return False


def encode_response(resp: InferenceResponse, tensors: dict[str, np.ndarray],
                    binary: set[str]) -> tuple[bytes, int | None]:
    """Response body and, when any output is binary, the JSON header length."""
    tail = []
    for out in resp.outputs:
        arr = tensors[out.name]
        if out.name in binary:
            raw = tensor_bytes(arr)
            out.parameters = {**(out.parameters or {}), "binary_data_size": len(raw)}
            tail.append(raw)
        else:
            out.data = arr.reshape(-1).tolist()
    return join_body(resp.model_dump_json(exclude_none=True).encode(), tail)
