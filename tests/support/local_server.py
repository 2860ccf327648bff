"""`noisestop serve` in a subprocess on a free loopback port, as a user starts it: for the
service tests and, from a source checkout, the benchmarks that load a real server."""
from __future__ import annotations

import json
import os
import secrets
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from typing import Any

from service.auth import ENV_TOKEN


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class LocalServer:
    """`noisestop serve` in a subprocess on 127.0.0.1 with a fresh token (or none, with
    `no_auth=True`, which the server then needs as `--no-auth`); stopped by SIGTERM.

    By default the subprocess calls `service.serve.run` with `serve_kwargs`; with `argv`
    (the command's options, e.g. ["--max-batch", "2"]) it runs the command line itself,
    `noisestop serve --model M --host 127.0.0.1 --port P ...`, for one model (None: the
    bundled one)."""

    def __init__(self, models: dict[str, str | None], *, port: int | None = None,
                 token: str | None = None, startup_timeout: float = 120.0,
                 env: dict[str, str] | None = None, address_space: int | None = None,
                 no_auth: bool = False, argv: list[str] | None = None, **serve_kwargs: Any) -> None:
        if argv is not None and (len(models) != 1 or serve_kwargs):
            raise ValueError("the command line serves one model, its options in argv")
        self.argv = argv
        self.models = {k: (None if v is None else str(v)) for k, v in models.items()}
        self.port = port or free_port()
        if no_auth and token is not None:
            raise ValueError("a token and no_auth: choose one")
        self.token = None if no_auth else (token or secrets.token_urlsafe(24))
        if no_auth and argv is None:
            serve_kwargs["no_auth"] = True
        self.url = f"http://127.0.0.1:{self.port}"
        self.startup_timeout = startup_timeout
        self.env = env or {}
        self.serve_kwargs = serve_kwargs
        self.address_space = address_space     # RLIMIT_AS of the server process, bytes (None: no limit)
        self.process: subprocess.Popen | None = None
        self._log = tempfile.TemporaryFile()

    def __enter__(self) -> "LocalServer":
        code = ("import json, logging, sys; logging.basicConfig(level=logging.INFO, stream=sys.stderr); "
                "from service.serve import run; a = json.loads(sys.argv[1]); "
                "run(a['models'], '127.0.0.1', a['port'], **a['kwargs'])")
        arg = json.dumps({"models": self.models, "port": self.port, "kwargs": self.serve_kwargs})
        env = {**os.environ, **self.env}
        env.pop("NOISESTOP_TOKEN_FILE", None)
        env.pop(ENV_TOKEN, None)
        if self.token is not None:
            env[ENV_TOKEN] = self.token
        command = [sys.executable, "-c", code, arg]
        if self.argv is not None:
            (model,) = self.models.values()
            command = [sys.executable, "-m", "service.cli", "serve", *(["--model", model] if model else []),
                       "--host", "127.0.0.1", "--port", str(self.port), *self.argv,
                       *(["--no-auth"] if self.token is None else [])]
        self.process = subprocess.Popen(command, env=env,
                                        stdout=subprocess.DEVNULL, stderr=self._log,
                                        preexec_fn=self._limit if self.address_space else None)
        deadline = time.monotonic() + self.startup_timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"server exited with status {self.process.returncode}:\n{self.log()}")
            try:
                with urllib.request.urlopen(self.url + "/v2/health/ready", timeout=1) as r:
                    if r.status == 200:
                        return self
            except (urllib.error.URLError, ConnectionError, TimeoutError):
                time.sleep(0.2)
        self.__exit__(None, None, None)
        raise RuntimeError(f"server not ready after {self.startup_timeout} s:\n{self.log()}")

    def _limit(self) -> None:
        import resource
        resource.setrlimit(resource.RLIMIT_AS, (self.address_space, self.address_space))

    def memory(self) -> dict[str, int]:
        """The server process's peak and current resident and virtual memory, bytes (Linux)."""
        assert self.process is not None
        fields = {"VmHWM": "peak_rss", "VmRSS": "rss", "VmPeak": "peak_vm", "VmSize": "vm"}
        out = {}
        with open(f"/proc/{self.process.pid}/status") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key in fields:
                    out[fields[key]] = int(value.split()[0]) * 1024
        return out

    def terminate(self, timeout: float = 60.0) -> int:
        """SIGTERM, then wait for the graceful shutdown; the exit status."""
        assert self.process is not None
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
        return self.process.wait(timeout)

    def __exit__(self, *exc: Any) -> None:
        if self.process is not None and self.process.poll() is None:
            try:
                self.terminate(timeout=30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()

    def log(self) -> str:
        self._log.seek(0)
        return self._log.read().decode(errors="replace")
