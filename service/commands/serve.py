"""`noisestop serve`: the verdict service (service.serve) with its limits."""
from __future__ import annotations

import argparse

from learning.names import OFFSET_LIMIT
from noisefeat.bounds import MIN_SIDE

from . import arguments as arg


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="serve verdicts over HTTP (Open Inference Protocol v2)")
    p.add_argument("--model", action="append", default=None, metavar="[NAME=]PATH",
                   help="model bundle to serve, optionally under NAME; repeat for several (the "
                        "first is also served as 'default'); none: the bundled model")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on; anything but loopback needs a token")
    p.add_argument("--port", type=arg.int_in(0, 65535), default=8000)
    p.add_argument("--token-file", default=None,
                   help="file holding the bearer token (default: $NOISESTOP_TOKEN, "
                        "else the file $NOISESTOP_TOKEN_FILE names)")
    p.add_argument("--no-auth", action="store_true",
                   help="serve without a token, on a loopback address only (without a token and "
                        "without this flag, serve refuses to start)")
    p.add_argument("--max-body-bytes", type=arg.int_in(1, 1 << 40), default=None,
                   help="largest request body (default: $NOISESTOP_MAX_BODY_BYTES or 64 MiB)")
    p.add_argument("--max-batch", type=arg.int_in(1, 1 << 20), default=None,
                   help="most blocks per request (default: $NOISESTOP_MAX_BATCH or 1024)")
    p.add_argument("--max-block-side", type=arg.int_in(MIN_SIDE, arg.MAX_SIDE), default=None,
                   help="longest block side accepted, in pixels (default: $NOISESTOP_MAX_BLOCK_SIDE or "
                        "2048); larger blocks are refused with 413 before any work")
    p.add_argument("--max-pixels", type=arg.int_in(MIN_SIDE, 1 << 31), default=None,
                   help="pixels of one request, blocks x height x width (default: $NOISESTOP_MAX_PIXELS "
                        "or 4194304); over it: 413")
    p.add_argument("--memory-budget", type=arg.int_in(1 << 20, 1 << 44), default=None,
                   help="bytes of working memory all requests in flight may take together (default: "
                        "$NOISESTOP_MEMORY_BUDGET or what one request of --max-body-bytes takes, 16x its "
                        "body); a request waits for its share, then gets 503")
    p.add_argument("--threads", type=arg.int_in(1, 256), default=2,
                   help="requests classified at the same time")
    p.add_argument("--torch-threads", type=arg.int_in(1, 256), default=1,
                   help="torch threads for each request being classified (default 1: requests "
                        "already run --threads at a time)")
    p.add_argument("--limit-concurrency", type=arg.int_in(1, 65536), default=64,
                   help="most requests in flight; more are answered 503 with Retry-After (health "
                        "probes and /metrics are never refused; default 64)")
    p.add_argument("--max-connections", type=arg.int_in(1, 65536), default=1024,
                   help="most open connections, idle ones included (default 1024)")
    p.add_argument("--header-timeout", type=arg.seconds, default=10.0,
                   help="seconds a connection has to send a request's headers, from opening or from "
                        "its previous response (default 10; slow-header clients are closed)")
    p.add_argument("--body-timeout", type=arg.seconds, default=30.0,
                   help="seconds a request body may stall before a 408 (default 30)")
    p.add_argument("--body-deadline", type=arg.seconds, default=None,
                   help="seconds a whole request body may take to arrive, from its headers (default: "
                        "$NOISESTOP_BODY_DEADLINE or 120); over it: 408")
    p.add_argument("--min-body-rate", type=arg.int_in(1, 1 << 40), default=None,
                   help="bytes a second a request body must average after --body-grace (default: "
                        "$NOISESTOP_MIN_BODY_RATE or 65536); slower: 408")
    p.add_argument("--body-grace", type=arg.float_in(0.0, 3600.0), default=None,
                   help="seconds before --min-body-rate applies (default: $NOISESTOP_BODY_GRACE or 10)")
    p.add_argument("--keep-alive", type=arg.int_in(1, 3600), default=5,
                   help="seconds an idle kept-alive connection stays open (default 5)")
    p.add_argument("--offset", type=arg.offset, default=None,
                   help="decision offset for every model served (default: each model's calibrated "
                        f"offset; range +-{OFFSET_LIMIT:g}); a request's own 'offset' parameter overrides it")
    p.add_argument("--tau", type=arg.tau, default=None,
                   help=arg.TAU_HELP.replace("default %(default)s", "default: each model's calibrated tau")
                   + "; a request's own 'tau' parameter overrides it")
    p.add_argument("--graceful-timeout", type=arg.seconds, default=30.0,
                   help="seconds SIGTERM (or SIGHUP) waits for requests in flight")
    p.set_defaults(handler=cmd_serve)


def cmd_serve(args: argparse.Namespace) -> int:
    from noisefeat.extras import require_extra

    require_extra("serve")
    from renderer.client.token import resolve_token
    # the token before the server's imports (seconds of them): a bad one is one line at once
    secret = resolve_token(token_file=args.token_file)
    from service.serve import parse_model_specs, run
    run(parse_model_specs(args.model), args.host, args.port, token=secret,
        max_body_bytes=args.max_body_bytes, max_batch=args.max_batch,
        inference_threads=args.threads, graceful_timeout=args.graceful_timeout, offset=args.offset,
        max_block_side=args.max_block_side, max_pixels=args.max_pixels,
        limit_concurrency=args.limit_concurrency, max_connections=args.max_connections,
        header_timeout=args.header_timeout, body_timeout=args.body_timeout, keep_alive=args.keep_alive,
        memory_budget=args.memory_budget, torch_threads=args.torch_threads, no_auth=args.no_auth,
        body_deadline=args.body_deadline, min_body_rate=args.min_body_rate, body_grace=args.body_grace,
        tau=args.tau)
    return 0
