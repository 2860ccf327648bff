"""The benchmark lab behind `noisestop bench`: `bench` runs the sections that measure the
figures of BENCHMARKS.md (`bench_features`, `bench_flip`, `bench_models`, `bench_passes`
for renders and passes, `bench_decisions` for the criteria, `bench_service`, the stability
matrix `stability`, the reliability suite `reliability` with its `attack`s) and rewrites
their marked parts; `timing` (medians, machine load), `loadtest` (a local server and
clients) and `charts` serve them. The verdict service never imports it.
"""
