#!/usr/bin/env bash
# The GPU benchmarks in one go, on a CUDA machine with the project importable and the embedded corpus generated
# (`dvc repro generate-corpus`): DTW-PA-JPE cost matrices on the GPU, then the fitting sweep (signer batches on the
# GPU vs per-clip fits on every CPU core of the same machine). Results go to $RESULTS (default benchmarks/results)
# as dtw_gpu.json and fitting_gpu.json, with a log of each.
#
#   bash benchmarks/gpu_benchmarks.sh [RESULTS]
set -uo pipefail
cd "$(dirname "$0")/.."
results=${1:-benchmarks/results}
mkdir -p "$results"
export PYTHONUNBUFFERED=1
python=${PYTHON:-python3}
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
"$python" -c "import sys, torch, numpy, numba; print(sys.version.split()[0], 'torch', torch.__version__, 'numpy',
numpy.__version__, 'numba', numba.__version__, 'cuda', torch.cuda.is_available())"
start=$(date +%s)
"$python" -c "from m3t.body.anny_body import AnnyBody; AnnyBody()" 2>&1 | tail -n 2
echo "body model ready in $(( $(date +%s) - start )) s"
timeout "${DTW_TIMEOUT:-240}" "$python" benchmarks/bench_dtw.py --device cuda --pairs "${DTW_PAIRS:-144}" \
    --gpu-batch "${DTW_GPU_BATCH:-144}" --out "$results/dtw_gpu.json" > "$results/dtw_gpu.log" 2>&1
echo "bench_dtw: exit $? ($(( $(date +%s) - start )) s)"; grep -E '"(pa_gpu|pa_new|jpe_new)_pairs_per_s"' "$results/dtw_gpu.json"
timeout "${FIT_TIMEOUT:-420}" "$python" benchmarks/bench_fitting.py --arms none --device cuda --gpu-tf32 \
    --gpu-solvers "${GPU_SOLVERS:-lbfgs_lockstep,lbfgs_batched,lbfgs}" \
    --gpu-batch-frames "${GPU_BATCH_FRAMES:-1024,8192}" --gpu-iterations "${GPU_ITERATIONS:-100,200}" \
    --gpu-workers "${GPU_WORKERS:-3}" --out "$results/fitting_gpu.json" 2>&1 | tee "$results/fitting_gpu.log" \
    | grep -E '^gpu_|Error|error' | cut -c1-400
echo "bench_fitting: exit $? ($(( $(date +%s) - start )) s)"
