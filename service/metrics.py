"""Prometheus metrics: HTTP request counts and latency per route, blocks classified, load times.

Each app gets its own CollectorRegistry, so several apps (tests, a bench next to a server)
never collide over metric names. Health probes are counted but kept out of the latency
histogram: a probe every few seconds would drown the percentiles that matter.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from fastapi import FastAPI
from prometheus_client import CollectorRegistry, Counter, Gauge
from prometheus_fastapi_instrumentator import Instrumentator
from prometheus_fastapi_instrumentator import metrics as pfi

HEALTH_PREFIX = "/v2/health"


class ServiceMetrics:
    """The service's own metrics, next to the instrumentator's HTTP metrics."""

    def __init__(self, registry: CollectorRegistry | None = None) -> None:
        self.registry = registry or CollectorRegistry()
        self.blocks = Counter("noisestop_blocks_classified", "Blocks (sub-images) classified",
                              ["model", "verdict"], registry=self.registry)
        self.nonfinite = Counter("noisestop_nonfinite_pixels", "NaN/Inf pixels received (read by "
                                 "the display rule: NaN/-Inf black, +Inf white)", ["model"],
                                 registry=self.registry)
        self.load_seconds = Gauge("noisestop_model_load_seconds", "Time taken to load each model",
                                  ["model"], registry=self.registry)

    def record(self, model: str, verdict: np.ndarray, parameters: dict[str, Any]) -> None:
        converged = int((verdict > 0).sum())
        self.blocks.labels(model, "converged").inc(converged)
        self.blocks.labels(model, "noisy").inc(len(verdict) - converged)
        bad = sum(sum(parameters.get(k, ())) for k in ("nonfinite_pixels", "nonfinite_quick_pixels"))
        if bad:
            self.nonfinite.labels(model).inc(bad)

    def instrument(self, app: FastAPI, **expose_kwargs: Any) -> None:
        """Add the HTTP middleware and the GET /metrics route (expose_kwargs go to app.get)."""
        inst = Instrumentator(registry=self.registry, should_group_status_codes=False)
        inst.add(pfi.requests(registry=self.registry))
        inst.add(_skip_health(pfi.latency(registry=self.registry, should_include_status=False,
                                          buckets=_LATENCY_BUCKETS)))
        inst.instrument(app).expose(app, endpoint="/metrics", **expose_kwargs)


_LATENCY_BUCKETS: Sequence[float] = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30)


def _skip_health(inner: Callable[[pfi.Info], None] | None) -> Callable[[pfi.Info], None]:
    def instrumentation(info: pfi.Info) -> None:
        if inner is not None and not info.modified_handler.startswith(HEALTH_PREFIX):
            inner(info)
    return instrumentation
