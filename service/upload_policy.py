"""How fast a request body must arrive: the stall, the whole-body deadline, the minimum rate.

Why: a slow uploader otherwise holds a request slot and memory for as long as it likes;
a body that breaks the policy is answered 408 (service.body_limit enforces it).
"""
from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass

from noisefeat.bounds import env_int, env_seconds

ENV_BODY_DEADLINE = "NOISESTOP_BODY_DEADLINE"
ENV_MIN_BODY_RATE = "NOISESTOP_MIN_BODY_RATE"
ENV_BODY_GRACE = "NOISESTOP_BODY_GRACE"


@dataclass(frozen=True)
class UploadPolicy:
    """How fast a request body must arrive (seconds; bytes a second). None: no such limit.

    `stall`: longest wait for the next bytes; `deadline`: the whole body, from its
    headers; `min_rate`: after `grace` seconds, the body must have averaged this rate
    since then (bytes received >= min_rate x (elapsed - grace))."""
    stall: float | None = 30.0
    deadline: float | None = 120.0
    min_rate: int | None = 64 * 1024
    grace: float = 10.0

    def __post_init__(self) -> None:
        for name in ("stall", "deadline"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))
                                      or not 0 < value <= 86400):
                raise ValueError(f"{name} must be a number of seconds in (0, 86400], got {value!r}")
        if isinstance(self.grace, bool) or not isinstance(self.grace, (int, float)) or not 0 <= self.grace <= 86400:
            raise ValueError(f"grace must be a number of seconds in [0, 86400], got {self.grace!r}")
        if self.min_rate is not None and (isinstance(self.min_rate, bool) or not isinstance(self.min_rate, int)
                                          or self.min_rate < 1):
            raise ValueError(f"min_rate must be a whole number of bytes a second >= 1, got {self.min_rate!r}")

    @classmethod
    def from_env(cls, stall: float | None = 30.0, deadline: float | None = None, min_rate: int | None = None,
                 grace: float | None = None, environ: Mapping[str, str] = os.environ) -> "UploadPolicy":
        """Explicit values win over NOISESTOP_BODY_DEADLINE / NOISESTOP_MIN_BODY_RATE /
        NOISESTOP_BODY_GRACE, which win over the defaults (120 s, 64 KiB/s, 10 s)."""
        return cls(stall=stall,
                   deadline=deadline if deadline is not None else env_seconds(environ, ENV_BODY_DEADLINE, 120.0,
                                                                              86400),
                   min_rate=min_rate if min_rate is not None else env_int(environ, ENV_MIN_BODY_RATE, 64 * 1024,
                                                                          minimum=1),
                   grace=grace if grace is not None else env_seconds(environ, ENV_BODY_GRACE, 10.0, 86400,
                                                                     zero=True))
