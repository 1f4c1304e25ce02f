#!/usr/bin/env bash
# The checks a session with a CUDA GPU runs, as one script (no GPU has been lent to this project yet, so
# every GPU figure is still unmeasured: docs/performance.md#gpu). It needs the checkout and
# ../shared/data/bench beside it; results go to $OUT (default ./gpu_check): the CUDA tests' log (the
# device fixture adds cuda:0 when Warp sees a GPU), the integration bench's record on the GPU, and the
# kernel study on the GPU. Each step has its own time limit so that one slow step leaves the others their time.
#   OUT=/path bash tools/gpu_check.sh
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-gpu_check}
mkdir -p "$OUT"
python -c "import warp as wp; wp.init(); assert wp.is_cuda_available(), 'no CUDA device: nothing to check'" || exit 2
nvidia-smi > "$OUT/nvidia-smi.txt" 2>&1
# every test the device fixture gives a cuda:0 case (tests/conftest.py), on CUDA only: the CPU half runs in CI
timeout 240 python -m pytest -q tests -k "cuda" > "$OUT/pytest_cuda.txt" 2>&1
echo "pytest (cuda): rc $?"
timeout 150 python tools/bench_integrate.py --device cuda --skip-numpy --repeats 5 --record-dir "$OUT" \
    > "$OUT/bench_integrate_cuda.txt" 2>&1; echo "bench_integrate (cuda): rc $?"
timeout 150 python tools/kernel_study.py --device cuda --out "$OUT/kernel_study" \
    > "$OUT/kernel_study_cuda.txt" 2>&1; echo "kernel_study (cuda): rc $?"
tail -n 3 "$OUT"/*.txt
