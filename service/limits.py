"""Request size limits, enforced before a body is decoded (`Limits`).

The body limit is enforced as bytes arrive (service.body_limit). The batch limit (items per
request), the largest block side and the pixel budget of a request (noisefeat.bounds: a
3.8 MB request of [1, 8, 40000, 3] once took the server to 23.7 GB) are checked on the
declared tensor shapes, before any tensor data is converted (`Limits.check_shapes`,
oip.decode_tensors). The memory all requests in flight may claim together
(`Limits.memory_budget`) is admitted by service.memory_budget, from the estimates of
service.memory_cost.
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass

from noisefeat.bounds import DEFAULT_MAX_BLOCK_SIDE, DEFAULT_MAX_PIXELS, ENV as BOUNDS_ENV, MIN_SIDE, env_int

from .memory_cost import request_cost
from .oip import ApiError, RequestInput

ENV_MAX_BODY = "NOISESTOP_MAX_BODY_BYTES"
ENV_MAX_BATCH = "NOISESTOP_MAX_BATCH"
ENV_MAX_BLOCK_SIDE = BOUNDS_ENV["max_block_side"]
ENV_MAX_PIXELS = BOUNDS_ENV["max_pixels"]
ENV_MEMORY_BUDGET = "NOISESTOP_MEMORY_BUDGET"
DEFAULT_MAX_BODY = 64 * 1024 * 1024   # 16 blocks of 128x128 + quick as JSON take ~30 MB
DEFAULT_MAX_BATCH = 1024
#: by default one request of the largest body at a time, or many smaller ones at once
DEFAULT_MEMORY_BUDGET = request_cost(DEFAULT_MAX_BODY)


@dataclass(frozen=True)
class Limits:
    max_body_bytes: int = DEFAULT_MAX_BODY
    max_batch: int = DEFAULT_MAX_BATCH
    max_block_side: int = DEFAULT_MAX_BLOCK_SIDE
    max_pixels: int = DEFAULT_MAX_PIXELS
    #: working memory all requests in flight may claim together (None: the cost of one
    #: request of the largest body); see `service.memory_budget.MemoryBudget`
    memory_budget: int | None = None

    def __post_init__(self) -> None:
        for name in ("max_body_bytes", "max_batch", "max_block_side", "max_pixels"):
            value = getattr(self, name)
            least = MIN_SIDE if name in ("max_block_side", "max_pixels") else 1
            if isinstance(value, bool) or not isinstance(value, int) or value < least:
                raise ValueError(f"{name} must be a whole number >= {least}, got {value!r}")
        if self.memory_budget is None:
            object.__setattr__(self, "memory_budget", request_cost(self.max_body_bytes))
        elif isinstance(self.memory_budget, bool) or not isinstance(self.memory_budget, int) \
                or self.memory_budget < request_cost(self.max_body_bytes):
            raise ValueError(f"memory_budget must be a whole number of bytes >= {request_cost(self.max_body_bytes)} "
                             f"(what one request of max_body_bytes = {self.max_body_bytes} may take), "
                             f"got {self.memory_budget!r}")

    @classmethod
    def from_env(cls, max_body_bytes: int | None = None, max_batch: int | None = None,
                 environ: Mapping[str, str] = os.environ, *, max_block_side: int | None = None,
                 max_pixels: int | None = None, memory_budget: int | None = None) -> "Limits":
        """Explicit values win over the environment, which wins over the defaults."""
        def env(key: str, default: int) -> int:
            return env_int(environ, key, default, minimum=1)
        budget = memory_budget or (env(ENV_MEMORY_BUDGET, 0) or None)
        return cls(max_body_bytes=max_body_bytes or env(ENV_MAX_BODY, DEFAULT_MAX_BODY),
                   max_batch=max_batch or env(ENV_MAX_BATCH, DEFAULT_MAX_BATCH),
                   max_block_side=max_block_side or env(ENV_MAX_BLOCK_SIDE, DEFAULT_MAX_BLOCK_SIDE),
                   max_pixels=max_pixels or env(ENV_MAX_PIXELS, DEFAULT_MAX_PIXELS),
                   memory_budget=budget)

    def check_shapes(self, inputs: list[RequestInput]) -> None:
        """413 for an image tensor [N, H, W, C] whose block side or pixel count (N x H x W)
        is over the limit, judged on its declared shape alone."""
        for t in inputs:
            if len(t.shape) != 4:
                continue
            n, h, w = t.shape[:3]
            if max(h, w) > self.max_block_side:
                raise ApiError(413, f"input {t.name!r}: blocks of {h}x{w} pixels exceed the largest block "
                                    f"side of this server, max_block_side = {self.max_block_side} "
                                    f"(serve --max-block-side, {ENV_MAX_BLOCK_SIDE})")
            if n * h * w > self.max_pixels:
                raise ApiError(413, f"input {t.name!r}: {n} blocks of {h}x{w} are {n * h * w} pixels, over "
                                    f"the pixel budget of a request, max_pixels = {self.max_pixels} "
                                    f"(serve --max-pixels, {ENV_MAX_PIXELS}); send fewer blocks per request")
