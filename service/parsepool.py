"""Large JSON request headers are parsed in worker processes, each with a time budget.

Why: a JSON parser builds its objects holding the GIL, so in a thread it still stops the
event loop (health probes included) and every other request for as long as it runs: an
8 MiB body of nested lists took 6.7 s. In a separate process a parse costs the server only
the transfer of the text and of the decoded arrays, and a parse that runs past `seconds`
is ended (the worker is killed and replaced) and answered 413.

Headers up to `INLINE_BYTES` that open at most `INLINE_CONTAINERS` lists and objects (every
binary-tensor request's, small JSON ones: `parse_inline`) are parsed in the server's own
thread. A 255 kB body nested 11 deep, parsed there, moved other requests' p99 13x. Why
containers and not bytes or depth: a 16.3 kB body nested 11 deep parses in about 1 ms, but
it allocates some 7,600 lists, and a JSON parse's lists and dicts are what Python's cyclic
garbage collector counts: past about 700 live ones a collection runs,
and every few requests a full one walks the server's whole heap (300,000 objects with
torch: 150-330 ms holding the GIL, measured). A body under 700 containers triggers none
however it loops (measured: 0 collections in 3,000 parses of 264 containers; 3 full ones of
up to 158 ms for 1,272). Numbers and strings are not tracked, so a flat 16 kB tensor stays
inline. The count is of the bytes `[` and `{`, strings included: an upper bound, one C
scan. Writing into a worker and reading its answer share one deadline, and idle workers
that die are reaped at once.

Wire: the server writes an 8-byte length and the JSON text to the worker's stdin; the
worker answers an 8-byte length and a message: an 8-byte length, a small JSON document
(the request with its decoded arrays left out and described by dtype and shape, or the
error's status, message and headers), then the arrays' raw bytes. No pickle crosses the
pipe: what comes back is read as JSON and numpy buffers, never executed.
"""
from __future__ import annotations

import json
import logging
import os
import select
import struct
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass
from typing import Any

import anyio
import anyio.to_thread

import numpy as np

from .oip import DATATYPES, ApiError, InferenceRequest

log = logging.getLogger(__name__)

#: JSON headers larger than this go to a worker process: the costliest JSON this size
#: (nested lists, or valid tensor data) decodes in about 2 ms holding the GIL (measured,
#: docs/benchmarks/reliability.md "JSON bodies"); a binary request's header is far smaller
INLINE_BYTES = 16 * 1024
#: ... and opening at most this many lists and objects (the module docstring: well under the
#: garbage collector's 700, so that a parse on the server's thread never sets off a collection)
INLINE_CONTAINERS = 256
#: how often idle workers are checked for death (and reaped)
REAP_SECONDS = 0.5
#: default seconds a worker may spend on one request (serve: NOISESTOP_PARSE_SECONDS)
DEFAULT_PARSE_SECONDS = 10.0
ENV_PARSE_SECONDS = "NOISESTOP_PARSE_SECONDS"
_LEN = struct.Struct("<Q")


def parse_inline(head: bytes | bytearray | memoryview, inline_bytes: int = INLINE_BYTES) -> bool:
    """Whether a JSON header is cheap enough for the server's own thread: at most
    `inline_bytes`, and at most INLINE_CONTAINERS `[` and `{` (counted only when small)."""
    if len(head) > inline_bytes:
        return False
    text = head if isinstance(head, (bytes, bytearray)) else bytes(head)
    return text.count(b"[") + text.count(b"{") <= INLINE_CONTAINERS


@dataclass(frozen=True)
class ParseRules:
    """What a worker checks before it builds tensors (the server's limits and ranges)."""
    max_batch: int
    max_block_side: int
    max_pixels: int
    exposure: tuple[float, float]
    offset_limit: float


class _Worker:
    """One worker process and its pipes; used by one request at a time."""

    def __init__(self, rules: ParseRules) -> None:
        self.rules = rules
        self.proc = subprocess.Popen([sys.executable, "-m", "service.parsepool", json.dumps(asdict(rules))],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=None,
                                     env={**os.environ, "OMP_NUM_THREADS": "1"})
        assert self.proc.stdin is not None
        os.set_blocking(self.proc.stdin.fileno(), False)      # writes wait in select, with a deadline

    def call(self, head: bytes | bytearray | memoryview, seconds: float) -> tuple[Any, ...]:
        """The worker's answer, or ("timeout",) / ("died",) (the worker is then dead)."""
        assert self.proc.stdin is not None and self.proc.stdout is not None
        deadline = time.monotonic() + seconds
        try:
            self._write(_LEN.pack(len(head)), deadline)
            self._write(head, deadline)
            size = _LEN.unpack(self._read(_LEN.size, deadline))[0]
            return decode_answer(self._read(size, deadline))
        except TimeoutError:
            self.kill()
            return ("timeout",)
        except (OSError, EOFError, ValueError, KeyError, TypeError, struct.error):
            self.kill()
            return ("died",)

    def _write(self, data: bytes | bytearray | memoryview, deadline: float) -> None:
        """All of `data` into the worker within the deadline: a stopped worker fills the
        pipe and would hold the request (and its slot) for ever on a blocking write."""
        assert self.proc.stdin is not None
        fd = self.proc.stdin.fileno()
        view, sent = memoryview(data).cast("B"), 0
        while sent < len(view):
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([], [fd], [], left)[1]:
                raise TimeoutError
            try:
                sent += os.write(fd, view[sent:sent + (1 << 20)])
            except BlockingIOError:
                continue

    def _read(self, n: int, deadline: float) -> bytearray:
        """`n` bytes from the worker into one writable buffer (the arrays are views of it)."""
        assert self.proc.stdout is not None
        fd = self.proc.stdout.fileno()
        buf = bytearray(n)
        view, got = memoryview(buf), 0
        while got < n:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([fd], [], [], left)[0]:
                raise TimeoutError
            k = os.readv(fd, [view[got:got + (1 << 20)]])
            if not k:
                raise EOFError
            got += k
        return buf

    def alive(self) -> bool:
        return self.proc.poll() is None

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()
        for f in (self.proc.stdin, self.proc.stdout):
            try:
                f.close()          # type: ignore[union-attr]
            except OSError:
                pass


class ParsePool:
    """`workers` parse processes, started on first use (or by `start`), replaced when they die."""

    def __init__(self, rules: ParseRules, workers: int = 2, seconds: float = DEFAULT_PARSE_SECONDS) -> None:
        if not 0 < seconds <= 3600:
            raise ValueError(f"parse seconds must be in (0, 3600], got {seconds!r}")
        self.rules = rules
        self.seconds = seconds
        self._idle: list[_Worker] = []
        self._lock = threading.Lock()
        self._slots = anyio.CapacityLimiter(workers)
        self._count = workers
        self._closed = threading.Event()
        self._reaper: threading.Thread | None = None

    def start(self) -> None:
        """Start the workers now (blocking: run it in a thread), and the reaper."""
        with self._lock:
            while len(self._idle) < self._count:
                self._idle.append(_Worker(self.rules))
            if self._reaper is None:
                self._reaper = threading.Thread(target=self._reap, name="parse-reaper", daemon=True)
                self._reaper.start()

    def close(self) -> None:
        self._closed.set()
        with self._lock:
            for w in self._idle:
                w.kill()
            self._idle.clear()

    def _reap(self, every: float = REAP_SECONDS) -> None:
        """Idle workers that died (killed, out of memory) are reaped and replaced at once,
        not left as zombies until their slot is next used."""
        while not self._closed.wait(every):
            with self._lock:
                dead = [w for w in self._idle if not w.alive()]
                self._idle = [w for w in self._idle if w.alive()]
            for w in dead:
                w.kill()                        # waits: the zombie is gone
                log.warning("an idle JSON parse worker died (exit %s); a new one takes its place",
                            w.proc.returncode)
            if dead and not self._closed.is_set():
                fresh = [_Worker(self.rules) for _ in dead]
                with self._lock:
                    self._idle.extend(fresh)

    async def parse(self, head: bytes | bytearray | memoryview) -> InferenceRequest:
        """The request with its JSON tensor data as numpy arrays; ApiError as parse_request."""
        async with self._slots:
            answer = await anyio.to_thread.run_sync(self._call, head)
        if answer[0] == "ok":
            return answer[1]
        if answer[0] == "error":
            raise ApiError(answer[1], answer[2], headers=answer[3])
        if answer[0] == "timeout":
            raise ApiError(413, f"parsing this request's JSON took over {self.seconds:g} s (the time a request "
                                f"may take, {ENV_PARSE_SECONDS}); send binary tensors or flat data",
                           headers={"Connection": "close"})
        raise ApiError(503, "server could not parse this request (out of memory?); retry, or send a smaller one",
                       headers={"Retry-After": "1", "Connection": "close"})

    def _call(self, head: bytes | bytearray | memoryview) -> tuple[Any, ...]:
        with self._lock:
            worker = self._idle.pop() if self._idle else None
        if worker is None or not worker.alive():
            worker = _Worker(self.rules)
        answer = worker.call(head, self.seconds)
        if worker.alive():
            with self._lock:
                self._idle.append(worker)
        else:
            log.warning("a JSON parse worker was ended (%s); a new one takes its place", answer[0])
        return answer


# ------------------------------------------------------------------------- the wire


def encode_answer(answer: tuple[Any, ...]) -> list[bytes | memoryview]:
    """A worker's answer as the wire's parts (see the module docstring)."""
    if answer[0] != "ok":
        doc: dict[str, Any] = {"error": [answer[1], answer[2], answer[3]]}
        arrays: list[np.ndarray] = []
    else:
        req = answer[1]
        held = [i for i, t in enumerate(req.inputs) if isinstance(t.data, np.ndarray)]
        arrays = [np.ascontiguousarray(req.inputs[i].data) for i in held]
        described = [{"input": i, "dtype": a.dtype.str, "shape": list(a.shape)} for i, a in zip(held, arrays)]
        dumped = req.model_dump(exclude_none=True, exclude={"inputs": {i: {"data"} for i in held}})
        doc = {"request": dumped, "arrays": described}
    text = json.dumps(doc).encode()
    return [_LEN.pack(len(text)), text, *(memoryview(a).cast("B") for a in arrays)]


def decode_answer(blob: bytearray) -> tuple[Any, ...]:
    """The answer back from the wire's bytes: ("ok", InferenceRequest with numpy `data`,
    views of `blob`) or ("error", status, message, headers). ValueError if it does not add up."""
    (n,) = _LEN.unpack_from(blob, 0)
    doc = json.loads(bytes(memoryview(blob)[_LEN.size:_LEN.size + n]))
    if "error" in doc:
        status, message, headers = doc["error"]
        return ("error", int(status), str(message), dict(headers or {}))
    req = InferenceRequest.model_validate(doc["request"])
    offset = _LEN.size + n
    for m in doc["arrays"]:
        dtype, shape = np.dtype(m["dtype"]), tuple(int(d) for d in m["shape"])
        if dtype.kind not in "biuf":
            raise ValueError(f"unexpected array type {dtype} from a parse worker")
        count = int(np.prod(shape, dtype=np.int64))
        a = np.frombuffer(blob, dtype, count, offset).reshape(shape)
        offset += a.nbytes
        req.inputs[int(m["input"])].data = a   # type: ignore[assignment]
    if offset != len(blob):
        raise ValueError("a parse worker's answer has bytes left over")
    return ("ok", req)


# ------------------------------------------------------------------------- the worker side

def parse_in_worker(head: bytes, rules: ParseRules) -> tuple[Any, ...]:
    """What the server's own thread does with a small header (service.infer._decode_sync),
    up to the tensors: parse (depth first), parameters, shapes, batch, JSON data as arrays."""
    from .limits import Limits
    from .oip import _json_values, check_batch, may_hold_bools, number_param, parse_request
    try:
        req = parse_request(head)
        number_param(req.parameters, "exposure", 0.0, *rules.exposure)
        number_param(req.parameters, "offset", None, -rules.offset_limit, rules.offset_limit)
        number_param(req.parameters, "tau", None, 0.0, 1.0)
        Limits(max_batch=rules.max_batch, max_block_side=rules.max_block_side,
               max_pixels=rules.max_pixels).check_shapes(req.inputs)
        check_batch(req, rules.max_batch)
        scan = may_hold_bools(head)
        del head
        for t in req.inputs:
            if isinstance(t.data, list) and t.datatype in DATATYPES:
                t.data = _json_values(t.name, t.data, DATATYPES[t.datatype], scan)  # type: ignore[assignment]
        return ("ok", req)
    except ApiError as exc:
        return ("error", exc.status, exc.message, exc.headers)
    except MemoryError:
        return ("error", 503, "server out of memory for this request; retry, or send a smaller one",
                {"Retry-After": "1", "Connection": "close"})


#: the workers' scheduling niceness: a parse yields the CPU to inference threads, so one
#: client's costly bodies slow its own answers more than everyone else's
WORKER_NICE = 10


def _main() -> None:
    from .heap import release_memory
    try:
        os.nice(WORKER_NICE)
    except OSError:
        pass
    rules = ParseRules(**{k: tuple(v) if isinstance(v, list) else v for k, v in json.loads(sys.argv[1]).items()})
    inp, out = sys.stdin.buffer, sys.stdout.buffer
    while True:
        raw = inp.read(_LEN.size)
        if len(raw) < _LEN.size:
            return                      # the server went away
        head = inp.read(_LEN.unpack(raw)[0])
        parts = encode_answer(parse_in_worker(head, rules))
        del head
        out.write(_LEN.pack(sum(len(p) if isinstance(p, bytes) else p.nbytes for p in parts)))
        for part in parts:
            out.write(part)
        out.flush()
        del parts
        release_memory(0)


if __name__ == "__main__":
    _main()
