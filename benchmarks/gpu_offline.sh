#!/usr/bin/env bash
# The GPU measurements on an offline machine with an NVIDIA GPU: one whose Python 3.12 has torch and numba-cuda
# but reaches no package registry, so our other dependencies travel as wheels, and whose numpy 2.5 is replaced by
# the gpu extra's numpy<2.5 (numba-cuda 0.30.4 cannot compile a kernel beside numpy 2.5).
#
#   with a registry:  bash benchmarks/gpu_offline.sh wheels     # -> .gpu_wheels/ (~21 MB, ignored by git)
#   on the GPU:       bash benchmarks/gpu_offline.sh tests      # tests/test_cuda*.py on the GPU itself
#                     bash benchmarks/gpu_offline.sh bench gpu  # or precision, learners
#                     bash benchmarks/gpu_offline.sh train 0-1  # seeds, each evaluated
#                     bash benchmarks/gpu_offline.sh train 0 configs/train/experiments/rsl-gpu-timed.yaml  # shorter
#
# Each part stays inside 10 minutes (timeout PART_S seconds, default 560). bench PART: `msdgrasp bench gpu`
# (physics batches 1..16,384 and the whole task step, float64 and float32, against 200k agent steps/s),
# `precision` (float32 error, coarse spleen, full episode) or `learners` (does SB3 keep up?). train SEEDS [CONFIG]:
# `msdgrasp train --backend cuda` on rsl_ppo.yaml (or CONFIG), timed, each seed evaluated; the runs come back as one
# archive. tests: the kernels and the task against the CPU on real hardware (NUMBA_ENABLE_CUDASIM=0). Everything
# lands in $OUT (default logs/gpu), each part's log included, so a part killed at its limit still reports.
set -euo pipefail
cd "$(dirname "$0")/.."
PACKAGES=("numpy>=2.0,<2.5" "gymnasium==1.4.0" farama-notifications "stable-baselines3==2.9.2" "pydantic==2.14.4"
          "pydantic-core==2.50.5" annotated-types typing-inspection "rsl-rl-lib==5.5.1" "tensordict==0.15.3" pyvers
          GitPython gitdb smmap "meshio==5.3.5" pytest pluggy iniconfig packaging)

setup() {  # on the device: our wheels over its image (no dependency resolution: the image has the rest)
    python3 -m pip install -q --no-index --no-deps .gpu_wheels/*.whl
    python3 -m pip install -q --no-deps --no-build-isolation -e .
    export NUMBA_CACHE_DIR=/tmp/numba_cache RAY_USAGE_STATS_ENABLED=0 PYTHONUNBUFFERED=1
    OUT="${OUT:-logs/gpu}" && mkdir -p "$OUT"
    nvidia-smi --query-gpu=name,driver_version,clocks.max.sm --format=csv >"$OUT/gpu.txt"
    python3 -m pip list 2>/dev/null | grep -Ei "^(numba|numba-cuda|numpy|torch|rsl-rl-lib|stable.baselines3) " >>"$OUT/gpu.txt"
}

case "${1:-}" in
    wheels)
        rm -rf .gpu_wheels && mkdir .gpu_wheels
        python3 -m pip download -q --dest .gpu_wheels --no-deps --only-binary=:all: --python-version 3.12 \
            --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux2014_x86_64 "${PACKAGES[@]}"
        du -sh .gpu_wheels ;;
    bench)
        part="${2:?bench PART: gpu, precision or learners}"
        setup
        timeout "${PART_S:-560}" msdgrasp bench "$part" --out "$OUT/bench_$part.json" 2>&1 | tee "$OUT/bench_$part.log" || true ;;
    train)
        setup
        seeds="${2:?train SEEDS, e.g. 0-1}" config="${3:-configs/train/rsl_ppo.yaml}"  # (CONFIG from the repo root)
        name="train_$(basename "$config" .yaml)_$seeds"
        ( time timeout "${PART_S:-560}" msdgrasp train --backend cuda --config "$config" \
            --seeds "$seeds" --out "logs/$name" --quiet ) 2>&1 | tee "$OUT/$name.log" || true
        tar czf "$OUT/$name.tgz" "logs/$name" ;;
    tests)
        setup
        NUMBA_ENABLE_CUDASIM=0 timeout "${PART_S:-560}" python3 -m pytest tests/test_cuda_physics.py tests/test_cuda_task.py \
            -rs -q 2>&1 | tee "$OUT/tests.log" || true ;;
    *)
        echo "usage: bash benchmarks/gpu_offline.sh wheels | bench gpu|precision|learners | train SEEDS [CONFIG] | tests" >&2
        exit 2 ;;
esac
