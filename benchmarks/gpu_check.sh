#!/usr/bin/env bash
# The GPU check of docs/GPU.md, in about 10 minutes on a fresh GPU machine (`tox -e gpu` installs
# the package first and runs this; without tox, run it where `meshbench` and pytest are
# installed on a CUDA build of torch):
#   1. the device: stop with one line when torch sees no CUDA device;
#   2. the `gpu` tests (tests/test_gpu.py: CPU and CUDA agree in float64, a short training);
#   3. the ground truth of rod_falling and plate_cantilever (reused when present);
#   4. `meshbench bench --device cuda --json results/bench/gpu.json` (no solver section: the
#      solvers run on the CPU) and its table, with ratios to the CPU's results/bench/final.json,
#      in results/bench/gpu.txt;
#   5. a few `paper` epochs of the rod and the plate on CUDA, each cut to a few optimizer steps,
#      within the time left; prints their losses.
# Settings (environment): GPU_CHECK_MINUTES (10), GPU_CHECK_OUT (results/bench/gpu.json),
# GPU_CHECK_RUNS (runs/gpu-check), GPU_CHECK_EPOCHS (3), GPU_CHECK_ROD_STEPS (16),
# GPU_CHECK_PLATE_STEPS (8), GPU_CHECK_IMPL (fast; e.g. fast,reference to measure both
# engines, twice the bench's time), GPU_CHECK_BENCH_ARGS (more `meshbench bench` options),
# GPU_CHECK_DEVICE (cuda; cpu runs the same steps on the CPU, to test this script), PYTHON
# (python); MESHBENCH_DATA as everywhere.
set -euo pipefail
cd "$(dirname "$0")/.."
MINUTES=${GPU_CHECK_MINUTES:-10}
OUT=${GPU_CHECK_OUT:-results/bench/gpu.json}
RUNS=${GPU_CHECK_RUNS:-runs/gpu-check}
EPOCHS=${GPU_CHECK_EPOCHS:-3}
IMPL=${GPU_CHECK_IMPL:-fast}
DEVICE=${GPU_CHECK_DEVICE:-cuda}
read -r -a BENCH_ARGS <<< "${GPU_CHECK_BENCH_ARGS:-}"
PY=${PYTHON:-python}
declare -A STEPS=([rod_falling]=${GPU_CHECK_ROD_STEPS:-16}
                  [plate_cantilever]=${GPU_CHECK_PLATE_STEPS:-8})
meshbench() { "$PY" -m benchmarks.cli "$@"; }
step() { echo; echo "== $(date -u +%H:%M:%S) [${SECONDS}s] $*"; }

step "device"
"$PY" - "$DEVICE" <<'EOF'
import sys

import torch

if sys.argv[1] == "cpu":
    print("GPU_CHECK_DEVICE=cpu: every step on the CPU (a test of this script)")
    sys.exit(0)
if not torch.cuda.is_available():
    sys.exit(f"gpu_check: torch {torch.__version__} (CUDA build: {torch.version.cuda or 'none'}) "
             "sees no CUDA device; install the machine's CUDA build of torch (docs/GPU.md)")
p = torch.cuda.get_device_properties(0)
print(f"{p.name}, {p.total_memory / 2**30:.0f} GiB, compute capability {p.major}.{p.minor}, "
      f"CUDA {torch.version.cuda}, torch {torch.__version__}")
EOF

step "gpu tests"
"$PY" -m pytest -m gpu -q -rs -p no:cacheprovider tests/test_gpu.py

step "ground truth"
meshbench generate rod_falling plate_cantilever --no-progress

step "bench -> $OUT"
mkdir -p "$(dirname "$OUT")"
meshbench bench --device "$DEVICE" --impl "$IMPL" --no-solver --rounds 3 --budget 0.2 \
    --epoch-steps 3 --json "$OUT" ${BENCH_ARGS[@]+"${BENCH_ARGS[@]}"}
base=results/bench/final.json  # the CPU's measurement (its fast engine), for the ratios
compare=()
if [[ -f $base ]]; then compare=(--compare "$base" --compare-impl fast); fi
meshbench bench --report "$OUT" ${compare[@]+"${compare[@]}"} > "${OUT%.json}.txt"
cat "${OUT%.json}.txt"

for case in rod_falling plate_cantilever; do
    left=$((MINUTES * 60 - SECONDS))
    if [[ $case == rod_falling ]]; then left=$((left / 2)); fi  # the plate's take longer
    step "paper epochs of $case: $EPOCHS of ${STEPS[$case]} optimizer steps, ${left}s at most"
    if ((left < 30)); then
        echo "gpu_check: no time left for $case (GPU_CHECK_MINUTES=$MINUTES)"
        continue
    fi
    rm -rf "$RUNS/$case"
    timeout --signal=INT "$left" "$PY" -m benchmarks.cli train --case "$case" \
        --model meshodenet --preset paper --epochs "$EPOCHS" \
        --set "train.max_batches=${STEPS[$case]}" --device "$DEVICE" --out "$RUNS/$case" \
        --no-progress || echo "gpu_check: $case stopped (exit $?); its finished epochs:"
    if [[ -f $RUNS/$case/history.csv ]]; then cut -d, -f1,2,3,7 "$RUNS/$case/history.csv"; fi
done
step "done: $OUT"
