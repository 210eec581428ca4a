#!/usr/bin/env bash
# The checks that need a CUDA device, in one run: the tests marked gpu (the training steps without host reads among
# them, under torch.cuda.set_sync_debug_mode("error"), and the steps captured as CUDA graphs), then the CUDA benchmarks
# (training step in 32-true and bf16-mixed, default and sync-free paths, eager, compiled per network and captured
# whole, side by side; the main job's loop eager, compiled, captured and syncing; the renderer). Logs go to $OUT
# (default: ./gpu-checks); the captured rows come last (they compile the longest).
# Run from the repository root on a machine where unicorn's dependencies are importable, or where a kit made by
# benchmarks/gpu_kit.sh lies (see gpu_env.sh):
#   bash benchmarks/gpu_checks.sh [PART ...]
# PART: tests, steps, compiled, render, rate, captured (the captured steps and the captured loop, first as CUDA
# graphs of the eager kernels, model.compile=cudagraphs, which compiles in the time of the tracing, then of inductor's
# kernels, reduce-overhead; their eager rows are those of steps and rate); default all, in that order. Name the parts
# in the order to run them where the time on the GPU is short, and bound each command with GPU_CHECKS_LIMIT (seconds;
# a command that runs over is stopped and the next one runs): compiling the captured steps takes minutes
# (docs/performance.md, "CUDA").
set -uo pipefail
all=(tests steps compiled render rate captured)
parts=("$@")
[ ${#parts[@]} -gt 0 ] || parts=("${all[@]}")
for part in "${parts[@]}"; do
  [[ " ${all[*]} " == *" $part "* ]] || { echo "gpu_checks.sh: unknown part $part (${all[*]})" >&2; exit 2; }
done
limit=${GPU_CHECKS_LIMIT:-0}
py() { if [ "$limit" -gt 0 ]; then timeout "$limit" python3 "$@"; else python3 "$@"; fi; }
out=${OUT:-gpu-checks}
export PYTHONUNBUFFERED=1
source "$(dirname "$0")/gpu_env.sh" || exit 1
python3 -c "import torch" 2>/dev/null || {
  echo "gpu_checks.sh: torch is not importable: activate unicorn's environment, or make a kit (gpu_kit.sh)" >&2; exit 2; }
python3 -c "import sys, torch; sys.exit(0 if torch.cuda.is_available() else 1)" || {
  echo "gpu_checks.sh: no CUDA device here (torch.cuda.is_available() is False): run it on a GPU machine" >&2; exit 2; }
mkdir -p "$out"
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv | tee "$out/device.txt"
python3 -c "import torch; print('torch', torch.__version__, torch.cuda.get_device_name())" | tee -a "$out/device.txt"
for part in "${parts[@]}"; do
  echo "== $part ($(date -u +%H:%M:%S))"
  case $part in
  tests)
    py -m pytest -m gpu tests -q -p no:cacheprovider 2>&1 | tee "$out/gpu_tests.log" ;;
  steps)
    py benchmarks/bm_train_step.py --device cuda --models tiny small --repeats 20 --precision 32-true bf16-mixed --paths default sync-free 2>&1 | tee "$out/bm_train_step.log" ;;
  compiled)
    py benchmarks/bm_train_step.py --device cuda --models small --repeats 20 --warmup 5 --compile none default reduce-overhead 2>&1 | tee "$out/bm_train_step_compile.log" ;;
  render)
    py benchmarks/bm_render.py --device cuda --quick 2>&1 | tee "$out/bm_render.log" ;;
  rate)
    py benchmarks/bm_train_rate.py --steps 400 --repeats 1 --variant "compiled model.compile=default" --variant "syncing optim.sync_free=false" trainer=gpu 2>&1 | tee "$out/bm_train_rate.log" ;;
  captured)
    for mode in cudagraphs reduce-overhead; do
      py benchmarks/bm_train_step.py --device cuda --models small --repeats 20 --warmup 5 --paths sync-free --compile step:$mode 2>&1 | tee "$out/bm_train_step_captured_$mode.log"
      py benchmarks/bm_train_rate.py --steps 600 --warmup 200 --repeats 1 trainer=gpu model.compile=$mode model.compile_scope=step 2>&1 | tee "$out/bm_train_rate_captured_$mode.log"
    done ;;
  esac
done
