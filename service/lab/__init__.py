"""The benchmark lab behind `noisestop bench`: the figures of BENCHMARKS.md (`bench`, and
`bench_decisions`, `bench_passes`, `bench_service` for the criteria, the render passes and
the service), the load test and local server (`loadtest`), the stability matrix
(`stability`), the reliability suite and its attacks (`reliability`, `attack`), and charts
(`charts`). The verdict service never imports it.
"""
