"""Attack scenarios against a running verdict server, bounded and on loopback only.

Each function drives one kind of abuse the attack found or the hardening must survive, and
returns what happened as plain numbers, so that tests assert on them and `noisestop bench
reliability` reports them (BENCHMARKS.md "Reliability"). One module per kind:

* `wire`: the client side (`post`, `timed_get`, `wait_closed`), loopback http:// only;
* `connections`: `idle_flood` (N connections that send nothing or half a request line,
  while health probes and one inference are timed; then how long the server takes to
  close them), `slow_headers` (one header byte at a time, slowloris, until the server
  hangs up), `stalled_body` (headers, then part of the body, then silence: 408),
  `over_the_limit` (`limit` requests held in flight, one more: 503, and a probe: 200),
  `protocol_error`;
* `uploads`: `slow_upload`, `normal_latency_under_slow_uploads`, `burst_then_stall`;
* `bodies`: the hostile bodies, made (`worst_shapes`: the largest and oddest requests the
  limits allow, and some they refuse; the costliest JSON; nested and valid JSON bodies
  around the parse pool's threshold);
* `hostile_bodies`: those bodies sent (`run_worst_shapes`, `costly_json_loop`, ...).

Everything is importable from here (`from benchmarks import attack; attack.post(...)`).
Nothing here sends more than a few hundred megabytes or runs longer than a minute.
"""
from __future__ import annotations

from .bodies import (binary_request, bound_json, costliest_valid_json, nested_json, nested_json_255k,
                     nested_json_request, nested_json_request_62, valid_halves_json, valid_json_255k, worst_shapes)
from .connections import MAX_CONNECTIONS, idle_flood, over_the_limit, protocol_error, slow_headers, stalled_body
from .hostile_bodies import costly_json_loop, duplicate_keys, nested_over_budget, run_worst_shapes
from .uploads import burst_then_stall, normal_latency_under_slow_uploads, slow_upload
from .wire import loopback_address, post, status_of, timed_get, wait_closed

__all__ = ["MAX_CONNECTIONS", "binary_request", "bound_json", "burst_then_stall", "costliest_valid_json",
           "costly_json_loop", "duplicate_keys", "idle_flood", "loopback_address", "nested_json",
           "nested_json_255k", "nested_json_request", "nested_json_request_62", "nested_over_budget",
           "normal_latency_under_slow_uploads", "over_the_limit", "post", "protocol_error", "run_worst_shapes",
           "slow_headers", "slow_upload", "stalled_body", "status_of", "timed_get", "valid_halves_json",
           "valid_json_255k", "wait_closed", "worst_shapes"]
