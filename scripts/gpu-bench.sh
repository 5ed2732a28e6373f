#!/usr/bin/env bash
# The GPU checks of the fast-bounce work in one call, for a lent GPU machine (the `device` tool):
# on cuda_ad_rgb, the benchmark (cost per spp against brdf and Mitsuba's path, rays/s, the cost breakdown) and the
# equal-spp checks (`validate --quick`), packed into one archive, $OUT/gpu-results.tgz (the tool brings back at most
# eight files), or results/gpu/ when OUT is unset.
#
# Here, once:  ../shared/tools/gpu-wheels.sh          (writes .whl/: drjit and mitsuba)
#              python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#                --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 -d .whl OpenEXR flip-evaluator
# Device:      run(command="bash scripts/gpu-bench.sh", carry=[".whl"], timeout_s=590)
# The project's scenes are benchmarked (the shared ones do not travel); GPU_BENCH_SCENES overrides the list.
set -euo pipefail
source "$(dirname "$0")/gpu-env.sh"
results=$(mktemp -d)
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | tee "$results/device.txt"
scenes=${GPU_BENCH_SCENES:-cornell:1,door-ajar:1,glossy-box:1}
status=0
timeout 330 python3 -m guiding bench --variant cuda_ad_rgb --scenes "$scenes" --passes 8 --out "$results/bench" \
  2>&1 | tee "$results/bench.log" || status=1
timeout 200 python3 -m guiding validate --variant cuda_ad_rgb --quick --out "$results/validate" \
  2>&1 | tee "$results/validate.log" || status=1
if [ -n "${OUT:-}" ]; then
  tar czf "$OUT/gpu-results.tgz" -C "$results" .
else
  mkdir -p results/gpu && cp -r "$results"/. results/gpu/
fi
exit $status
