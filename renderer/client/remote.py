"""A small Open Inference Protocol v2 client for a noisestop verdict server (stdlib only).

`RemoteModel` scores blocks like a local model over HTTP (DESIGN "HTTP API"; never imports
`service`), by default with the binary tensor extension through the server's codec (`oip_codec`).
A 4xx answer raises ValueError and a 5xx ConnectionError, quoting the server's ``{"error": ...}``;
connection failures and a 503 with Retry-After are retried a bounded number of times, a timeout
or other error answer is not.
"""
from __future__ import annotations

import http.client
import json
import logging
import time
import urllib.error
import urllib.parse
import urllib.request
from typing import Any

import numpy as np

from ..settings import ROW
from .oip_codec import DATATYPES, HEADER_LENGTH, WireError, join_body, read_tensor, split_body, tensor_bytes
from .token import check_token, resolve_token

logger = logging.getLogger(__name__)

default_token = resolve_token       # called bare: the environment's token, by the server's own rule


class RemoteModel:
    """A verdict model behind an OIP v2 server, used like a local `learning` Model.

    `url`: the server's base URL (``http://host:8000``); `model`: its name (noisestop serves ``default``);
    `token`: bearer token (default: NOISESTOP_TOKEN / NOISESTOP_TOKEN_FILE); `binary`: the binary tensor
    extension (else plain JSON lists, ~10x larger); `batch_size`: most blocks per request.
    """

    input = "features"  # the server computes features from blocks + quick: send the quick blocks

    def __init__(self, url: str, model: str = "default", token: str | None = None, binary: bool = True,
                 timeout: float = 30.0, retries: int = 3, backoff: float = 0.25, batch_size: int = 64,
                 tau: float | None = None) -> None:
        parsed = urllib.parse.urlparse(url)
        if parsed.scheme not in ("http", "https") or not parsed.netloc:
            raise ValueError(f"server URL must look like http://host:port, got {url!r}")
        if not model or "/" in model:
            raise ValueError(f"model name must be a non-empty name without '/', got {model!r}")
        if timeout <= 0 or retries < 0 or batch_size < 1:
            raise ValueError(f"timeout must be > 0, retries >= 0 and batch_size >= 1, got "
                             f"{timeout!r}, {retries!r}, {batch_size!r}")
        self.url = url.rstrip("/")
        self.model = model
        self.tau = tau          # the noise target sent with every request (None: the server's)
        if token is not None:
            check_token(token, "the server token (token argument)")
        self.token = token if token is not None else default_token()
        self.binary, self.timeout = bool(binary), float(timeout)
        self.retries, self.backoff, self.batch_size = int(retries), float(backoff), int(batch_size)
        self.requests = 0  # HTTP requests sent (retries included)
        host = parsed.hostname or ""
        self._loopback = host == "localhost" or host.startswith("127.") or host == "::1"
        self._opener_obj: urllib.request.OpenerDirector | None = None
        self._quick: str | None = None

    @property
    def _opener(self) -> urllib.request.OpenerDirector:
        """Built lazily, so the object pickles (Dask ships criteria to worker processes)."""
        if self._opener_obj is None:
            # a proxy from the environment must not swallow requests to this very machine
            self._opener_obj = urllib.request.build_opener(
                urllib.request.ProxyHandler({}) if self._loopback else urllib.request.ProxyHandler())
        return self._opener_obj

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_opener_obj": None}

    def __repr__(self) -> str:
        return f"RemoteModel({self.url!r}, model={self.model!r}, binary={self.binary})"

    # -- transport ---------------------------------------------------------------

    def _path(self, *parts: str) -> str:
        return self.url + "/" + "/".join(urllib.parse.quote(p, safe="") for p in parts)

    def _request(self, method: str, url: str, body: bytes | None = None,
                 headers: dict[str, str] | None = None) -> tuple[int, dict[str, str], bytes]:
        """(status, headers, body); HTTP error statuses are returned, not raised."""
        hdrs = {"Accept": "application/json", **(headers or {})}
        if self.token:
            hdrs["Authorization"] = f"Bearer {self.token}"
        attempt = 0
        while True:
            attempt += 1
            self.requests += 1
            req = urllib.request.Request(url, data=body, method=method, headers=hdrs)
            try:
                with self._opener.open(req, timeout=self.timeout) as resp:
                    return resp.status, {k.lower(): v for k, v in resp.headers.items()}, resp.read()
            except urllib.error.HTTPError as exc:
                with exc:
                    status, answer = exc.code, exc.read()
                    got = {k.lower(): v for k, v in (exc.headers or {}).items()}
                retry_after = got.get("retry-after", "")
                if status == 503 and retry_after.isdigit() and attempt <= self.retries:
                    # a busy server (its in-flight or memory limit) says when to come back
                    delay = min(float(retry_after), 30.0) + self.backoff * (attempt - 1)
                    logger.warning("%s %s: server busy (503); retry %d/%d in %.2f s", method, url, attempt,
                                   self.retries, delay)
                    time.sleep(delay)
                    continue
                return status, got, answer
            except (TimeoutError, urllib.error.URLError, ConnectionError, http.client.RemoteDisconnected,
                    http.client.BadStatusLine) as exc:
                reason = getattr(exc, "reason", exc)
                if isinstance(reason, TimeoutError):
                    raise ConnectionError(f"{method} {url}: no answer within {self.timeout:g} s") from exc
                if isinstance(exc, urllib.error.URLError) and not isinstance(reason, OSError):
                    raise ConnectionError(f"{method} {url}: {reason}") from exc
                if attempt > self.retries:
                    raise ConnectionError(f"{method} {url}: server unreachable after {attempt} attempt(s): "
                                          f"{reason}") from exc
                delay = self.backoff * 2 ** (attempt - 1)
                logger.warning("%s %s failed (%s); retry %d/%d in %.2f s", method, url, reason, attempt,
                               self.retries, delay)
                time.sleep(delay)
                continue
            except ValueError:      # http.client refusing a header: its message quotes it, token and all
                pass
            # only a refused request gets here: raised outside the handler, so not even as the context
            raise ValueError(f"{method} {url}: the request could not be sent (refused by http.client; its "
                             "headers, which hold the token, are not shown)")

    @staticmethod
    def _error_text(body: bytes) -> str:
        try:
            obj = json.loads(body)
        except (ValueError, UnicodeDecodeError):
            return body[:200].decode("utf-8", "replace").strip() or "(empty body)"
        for key in ("error", "detail"):
            if isinstance(obj, dict) and key in obj:
                return str(obj[key])
        return json.dumps(obj)[:200]

    def _check(self, method: str, url: str, status: int, body: bytes) -> None:
        if status >= 400:
            raise (ConnectionError if status >= 500 else ValueError)(
                f"{method} {url}: HTTP {status}: {self._error_text(body)}")

    # -- protocol ----------------------------------------------------------------

    def ready(self) -> bool:
        """Whether the server says the model is ready. Unreachable: ConnectionError ('not ready'
        and 'not there' differ); 401/403/404: ValueError; any other error status (Triton's 400,
        KServe's 503 while loading): not ready."""
        url = self._path("v2", "models", self.model, "ready")
        status, _, body = self._request("GET", url)
        if status in (401, 403, 404):
            self._check("GET", url, status, body)
        if status >= 400:
            return False
        try:
            obj = json.loads(body) if body else {}
        except ValueError:
            return True  # a 200 without JSON: KServe-style bare status
        return bool(obj.get("ready", True)) if isinstance(obj, dict) else True

    @property
    def quick(self) -> str:
        """The served model's input ('halves', or the quick image 'albedo', 'direct', 'none'),
        asked once from its metadata (a server that does not say wants albedo)."""
        if self._quick is None:
            params = self.metadata().get("parameters") or {}
            self._quick = str(params.get("quick", "albedo"))
        return self._quick

    @property
    def needs_quick(self) -> bool:
        return self.quick not in ("none", "halves")

    @property
    def needs_halves(self) -> bool:
        """The served model reads the half buffers ('even', 'odd') instead of the block."""
        return self.quick == "halves"

    def metadata(self) -> dict[str, Any]:
        """The model's metadata document (name, versions, platform, inputs, outputs)."""
        url = self._path("v2", "models", self.model)
        status, _, body = self._request("GET", url)
        self._check("GET", url, status, body)
        try:
            obj = json.loads(body)
        except ValueError:
            raise ValueError(f"GET {url}: metadata is not JSON: {body[:80]!r}") from None
        if not isinstance(obj, dict):
            raise ValueError(f"GET {url}: metadata is not a JSON object")
        return obj

    def infer(self, inputs: dict[str, np.ndarray], outputs: tuple[str, ...] = ("verdict", "score"),
              parameters: dict[str, Any] | None = None) -> dict[str, np.ndarray]:
        """One OIP infer call: named FP32 inputs in, named output arrays out; `parameters`
        are the request's (noisestop reads `exposure` and `offset`)."""
        url = self._path("v2", "models", self.model, "infer")
        tensors, tail = [], []
        for name, arr in inputs.items():
            a = np.ascontiguousarray(arr, dtype=DATATYPES["FP32"])
            t: dict[str, Any] = {"name": name, "shape": list(a.shape), "datatype": "FP32"}
            if self.binary:
                raw = tensor_bytes(a, "FP32")
                t["parameters"] = {"binary_data_size": len(raw)}
                tail.append(raw)
            else:
                t["data"] = a.reshape(-1).tolist()
            tensors.append(t)
        req: dict[str, Any] = {"inputs": tensors, "outputs": [{"name": o, "parameters": {"binary_data": self.binary}}
                                                              for o in outputs]}
        if parameters:
            req["parameters"] = parameters
        body, header_length = join_body(json.dumps(req, separators=(",", ":")).encode(), tail)
        hdrs = {"Content-Type": "application/octet-stream" if self.binary else "application/json"}
        if header_length is not None:
            hdrs[HEADER_LENGTH] = str(header_length)
        status, rhdrs, body = self._request("POST", url, body, hdrs)
        self._check("POST", url, status, body)
        return self._parse_outputs(url, rhdrs, body, outputs)

    @staticmethod
    def _parse_outputs(url: str, headers: dict[str, str], body: bytes,
                       wanted: tuple[str, ...]) -> dict[str, np.ndarray]:
        hlen = headers.get(HEADER_LENGTH.lower())
        try:
            header, tail = split_body(body, int(hlen) if hlen is not None else None)
        except ValueError as exc:      # not a number, or not within the answer
            raise ValueError(f"POST {url}: bad {HEADER_LENGTH} {hlen!r} ({exc})") from None
        try:
            resp = json.loads(header)
        except (ValueError, UnicodeDecodeError):
            raise ValueError(f"POST {url}: answer header is not JSON: {body[:80]!r}") from None
        outs = resp.get("outputs") if isinstance(resp, dict) else None
        if not isinstance(outs, list):
            raise ValueError(f"POST {url}: answer has no 'outputs' list")
        offset, result = 0, {}
        for o in outs:
            name, dt, shape = o.get("name"), o.get("datatype"), o.get("shape")
            if dt not in DATATYPES or not isinstance(shape, list):
                raise ValueError(f"POST {url}: output {name!r} has datatype {dt!r} / shape {shape!r}")
            size = (o.get("parameters") or {}).get("binary_data_size")
            if size is not None:
                try:
                    arr = read_tensor(tail, dt, shape, size, offset, f"output {name!r}")
                except WireError as exc:
                    raise ValueError(f"POST {url}: {exc}") from None
                offset += size
            else:
                data = o.get("data")
                if data is None:
                    raise ValueError(f"POST {url}: output {name!r} has neither data nor binary_data_size")
                arr = np.asarray(data, dtype=DATATYPES[dt]).reshape(shape)
            result[name] = arr
        missing = [w for w in wanted if w not in result]
        if missing:
            raise ValueError(f"POST {url}: answer lacks output(s) {missing}")
        return result

    def score_blocks(self, blocks: np.ndarray, quick: np.ndarray | None = None,
                     exposure: float = ROW["exposure"].default,
                     offset: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(verdict int8 [N], score float64 [N]) for linear RGB blocks [N, H, W, 3]: the
        server's stop rule at display `exposure` and at `offset` (None: the model's own)."""
        b = np.asarray(blocks)
        if b.ndim != 4 or b.shape[-1] != 3:
            raise ValueError(f"blocks must be [N, H, W, 3], got shape {b.shape}")
        if quick is not None and np.shape(quick) != b.shape:
            raise ValueError(f"quick blocks {np.shape(quick)} do not match blocks {b.shape}")
        return self._score({"blocks": b, **({} if quick is None else {"quick": np.asarray(quick)})},
                           exposure, offset)

    def score_halves(self, even: np.ndarray, odd: np.ndarray, exposure: float = ROW["exposure"].default,
                     offset: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """`score_blocks` for a `halves` model: the half-buffer means of N blocks, [N, H, W, 3] each."""
        a, b = np.asarray(even), np.asarray(odd)
        if a.ndim != 4 or a.shape[-1] != 3 or a.shape != b.shape:
            raise ValueError(f"even and odd must be two [N, H, W, 3] arrays of one shape, got {a.shape} "
                             f"and {b.shape}")
        return self._score({"even": a, "odd": b}, exposure, offset)

    def _score(self, tensors: dict[str, np.ndarray], exposure: float,
               offset: float | None) -> tuple[np.ndarray, np.ndarray]:
        given = {"exposure": exposure or None, "offset": offset, "tau": self.tau}     # exposure 0: not sent
        params = {k: float(v) for k, v in given.items() if v is not None}
        n = len(next(iter(tensors.values())))
        verdicts, scores = [np.zeros(0, np.int8)], [np.zeros(0, np.float64)]     # n may be 0
        for i in range(0, n, self.batch_size):
            inputs = {k: v[i:i + self.batch_size] for k, v in tensors.items()}
            rows = len(next(iter(inputs.values())))
            out = self.infer(inputs, parameters=params)
            v, s = out["verdict"].reshape(-1), out["score"].reshape(-1)
            if len(v) != rows or len(s) != len(v):
                raise ValueError(f"server returned {len(v)} verdicts / {len(s)} scores for {rows} blocks")
            if not np.isin(v, (-1, 1)).all():
                raise ValueError(f"server returned verdicts other than -1/+1: {np.unique(v)[:5].tolist()}")
            verdicts.append(v.astype(np.int8))
            scores.append(s.astype(np.float64))
        return np.concatenate(verdicts), np.concatenate(scores)
