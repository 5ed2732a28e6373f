#!/usr/bin/env bash
# config/gpu.yaml (the paper's resolutions and budgets on cuda_ad_rgb) in one call, for a machine with one GPU and
# the shared scenes (../shared/scenes or $GUIDING_SCENES). Packs results/gpu-paper's tables, figures and
# provenance (not the renders) into $OUT/gpu-paper.tgz when OUT is set (the `device` tool brings back few files).
#
# Wheels for a machine without an index, made here once: ../shared/tools/gpu-wheels.sh (writes .whl/).
set -euo pipefail
source "$(dirname "$0")/gpu-env.sh"
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
start=$(date +%s)
timeout "${GPU_PAPER_TIMEOUT:-590}" python3 -m snakemake --cores 4 --resources timing=1 gpu=1 \
  --configfile config/gpu.yaml --keep-going
echo "config/gpu.yaml: $(( $(date +%s) - start )) s"
if [ -n "${OUT:-}" ]; then
  tar czf "$OUT/gpu-paper.tgz" results/gpu-paper/tables results/gpu-paper/figures results/gpu-paper/provenance.*
fi
