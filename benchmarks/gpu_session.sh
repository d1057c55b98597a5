#!/usr/bin/env bash
# The GPU measurements as one command, for a machine held for a few minutes: the GPU check first (about 5 minutes
# on one H100), then the paper-scale pipeline on the GPU in the time left. The pipeline writes each stage's wall
# time as the stage finishes (runs/gpu_paper/pipeline.json), so a run cut off by the limit still reports the
# stages it finished; its log shows how far the cut stage got.
#
#   benchmarks/gpu_session.sh [SECONDS]     # both within SECONDS (default 540)
#
# Its plumbing runs on a CPU too, at a tiny size:
#   CHECK_ARGS="--device cpu --tiny" PIPELINE_ARGS="scale=smoke device=cpu" benchmarks/gpu_session.sh 300
#
# With no network there, build benchmarks/offline_kit.sh's kit first and set PYTHONPATH as it says. Writes to $OUT
# when it is set, else to benchmarks/results/: gpu_check.json and .log, gpu_pipeline.json (stage times) and .log.
set -uo pipefail

limit=${1:-540}
out=${OUT:-benchmarks/results}
python=${PYTHON:-python3}
experiment=${EXPERIMENT:-gpu_paper}
read -r -a check_args <<<"${CHECK_ARGS:-}"
read -r -a pipeline_args <<<"${PIPELINE_ARGS:-scale=paper_gpu device=cuda}"
mkdir -p "$out"
export PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
"$python" -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"

timeout --signal=INT --kill-after=15 $((limit * 55 / 100)) "$python" -m benchmarks.gpu_check "${check_args[@]}" >"$out/gpu_check.log" 2>&1
echo "gpu_check: exit status $? after ${SECONDS} s"
tail -n 25 "$out/gpu_check.log"

left=$((limit - SECONDS - 25))  # SIGINT lets the stage in flight checkpoint and the pipeline record what finished
timeout --signal=INT --kill-after=15 "$left" "$python" -m worldmodel.pipeline "experiment=$experiment" \
    "${pipeline_args[@]}" >"$out/gpu_pipeline.log" 2>&1
echo "pipeline: exit status $? after ${SECONDS} s"
if cp "runs/$experiment/pipeline.json" "$out/gpu_pipeline.json" 2>/dev/null; then
    cat "$out/gpu_pipeline.json"
else
    echo "pipeline: no stage finished"
fi
tr '\r' '\n' <"$out/gpu_pipeline.log" | grep -v '^\s*$' | tail -n 5
