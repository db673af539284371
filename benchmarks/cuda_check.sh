#!/usr/bin/env bash
# The GPU checks of issue 13 in one go, for a machine with a CUDA device (run from the repository root):
#   1. the tests marked `cuda` (every stage on the GPU against the CPU: tests/test_cuda.py and the others),
#   2. benchmarks/scaling.py --device cuda: time per stage against pixels (128² … 1024², the full TRI050S-PC
#      frame) and lights (4 … 48 at 256²), peak RSS and peak CUDA memory,
#   3. the full frame on the same machine's CPU (all its cores), for the CUDA/CPU ratio.
# Each part has its own time limit and the script goes on when one fails; everything lands in OUTDIR
# (machine.txt, cuda_tests.log, scaling_cuda.md/.log, fullframe_cpu.log).
#
# Usage: bash benchmarks/cuda_check.sh OUTDIR [WORKDIR]
#   DEVICE=cpu SIZES="128" LIGHTS="4" bash benchmarks/cuda_check.sh /tmp/out   # a dry run of the script on a CPU box
#   SIZES="256 full" LIGHTS="" CPU_FULL=0 bash benchmarks/cuda_check.sh OUTDIR  # tests and two sizes only
set -u
out=${1:?usage: cuda_check.sh OUTDIR [WORKDIR]}
work=${2:-/tmp/cuda_check}
py=${PYTHON:-python3}
device=${DEVICE:-cuda}
sizes=${SIZES:-128 256 512 1024 full}
lights=${LIGHTS-4 8 12 24 48}  # LIGHTS="" skips the light sweep
cpu_full=${CPU_FULL:-1}  # CPU_FULL=0 skips part 3
mkdir -p "$out" "$work"
export PYTHONUNBUFFERED=1

{
    date -u
    nvidia-smi -L 2>&1 || true
    nproc --all
    $py -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available() and torch.cuda.get_device_name(0))"
} 2>&1 | tee "$out/machine.txt"

echo "== tests marked cuda"
timeout 150 $py -m pytest -q -p no:cacheprovider -m cuda -rs --durations=10 tests/test_cuda.py \
    tests/recover/test_joint_solve.py tests/test_pipeline.py tests/acquisition/test_simulated.py 2>&1 \
    | tee "$out/cuda_tests.log"

echo "== scaling on $device"
# shellcheck disable=SC2086  # the sizes and lights are lists
timeout 330 $py benchmarks/scaling.py --device "$device" --sizes $sizes --lights $lights --work "$work/scaling" \
    --md "$out/scaling_$device.md" 2>&1 | tee "$out/scaling_$device.log"

echo "== the full frame on this machine's CPU"
if [[ " $sizes " == *" full "* && $cpu_full == 1 ]]; then
    timeout 90 $py benchmarks/scaling.py --device cpu --case full-frame --work "$work/scaling" 2>&1 \
        | tee "$out/fullframe_cpu.log"
fi
date -u | tee -a "$out/machine.txt"
