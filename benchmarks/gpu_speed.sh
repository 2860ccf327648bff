#!/bin/sh
# The speed figures on a GPU (docs/benchmarks/speed.md: equal time, cost per kept sample,
# cold start) in one run on a lent NVIDIA device, parts in order of worth, each under its own
# timeout so that a slow part leaves the others their time (about 11 minutes in all, in the
# 15 a session is lent; not yet run: no GPU was lent when it was written).
#
#   here:   sh ../shared/gpu/pack-site.sh .gpu/site.tar.xz
#   there:  the device tool, carrying .gpu/site.tar.xz:  sh benchmarks/gpu_speed.sh .gpu/site.tar.xz
#
# Writes under $OUT (else out/gpu): device.txt, and per part its JSON and log:
# equaltime_gpu.json (the default render against mi.render at equal time and to its quality,
# 1024x1024, max 4096: `benchmarks.bench_equal_time`), cost_gpu.json (the cost per kept
# sample in parts: `benchmarks.bench_cost`), cold.json (`noisestop render` against a cold
# mi.render script: `benchmarks.bench_cold`). Their tables: each module's md_* function.
set -u
site=$(mktemp -d)
tar -xJf "$1" -C "$site"
export PYTHONPATH="$site:$PWD" NOISESTOP_VARIANT=cuda_ad_rgb
out=${OUT:-out/gpu}
mkdir -p "$out"
nvidia-smi --query-gpu=name,memory.total --format=csv > "$out/device.txt" 2>&1
timeout 300 python3 -m benchmarks.bench_equal_time --size 1024 --no-make-run \
  --json "$out/equaltime_gpu.json" > "$out/equaltime.log" 2>&1
timeout 240 python3 -m benchmarks.bench_cost --size 1024 --max-spp 1024 \
  --scenes studio_preview,cornell_box,spot_stage --filter box,gaussian --repeats 1 \
  --json "$out/cost_gpu.json" > "$out/cost.log" 2>&1
timeout 100 python3 -c "
import json, sys
from benchmarks.bench_cold import cold_row
json.dump(cold_row(1024, 1024, 'cuda_ad_rgb', repeats=2), open(sys.argv[1], 'w'), indent=1)
" "$out/cold.json" > "$out/cold.log" 2>&1
ls -la "$out"
