"""The benchmarks behind `make bench` and `noisestop bench`, kept beside the packages, not in
them: they run from a source checkout and are neither installed nor in the serving image,
so nothing under noisefeat, learning, renderer or service imports them (the `bench`
command loads them from the checkout: service/commands/bench.py).

`bench` runs the sections that measure the figures of BENCHMARKS.md (`bench_features`,
`bench_flip`, `bench_models`, `bench_passes` for renders and passes, `bench_criteria`,
`bench_tradeoff` and `bench_step` for the stopping decisions, `bench_budget`,
`bench_observer`, `bench_service`, `bench_capacity`, the stability matrix `stability`, the
reliability suite `reliability` with `hardening` and the `attack` scenarios) and rewrites
their marked parts (`marked_sections`); `timing` (medians, machine load), `loadtest`
(closed-loop load), `openloop` (open-loop load) and `charts` serve them. No two modules
import each other around a circle (tests/project/test_layout.py). The local server, the
demo bundle and the requests come from the tests' helpers (tests/support).
"""
