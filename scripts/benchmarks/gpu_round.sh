#!/usr/bin/env bash
# One lent-GPU round for the long-movie issue, in one call (about 8 minutes on an H100/H200):
# the CUDA tests, the 500-frame movie record, where a block's time goes (gpu_timeline.py, with
# the default block and with 64 targets a block), the classical targets at 250,000 POIs, and a
# whole `stsdic run --device cuda` of the hourglass (fresh processes, first and second).
#
#   HG=.gpu/hourglass bash scripts/benchmarks/gpu_round.sh      # logs and records in $OUT
#
# Needs kornia's wheels in .whl/ (README: GPU) and, for the hourglass, its images in $HG.
set -uo pipefail
OUT=${OUT:-$PWD/gpu-out}
mkdir -p "$OUT"
export OUT PYTHONUNBUFFERED=1 OMP_WAIT_POLICY=PASSIVE STSDIC_GAP_LOG=$OUT/gaps.txt
t0=$SECONDS
TESTS="tests/test_cuda.py tests/test_triton.py tests/test_triton_solve.py" bash scripts/benchmarks/gpu_check.sh tests,movie \
  2>&1 | tail -40
export PYTHONPATH=/tmp/site:$PWD STSDIC_BENCH_CACHE=${STSDIC_BENCH_CACHE:-$PWD/.benchcache}
for bf in default 64; do
  extra=""; [[ $bf != default ]] && extra="--batch-frames $bf"
  timeout 100 python3 scripts/benchmarks/gpu_timeline.py --frames 120 $extra \
    --out "$OUT/timeline-$bf.txt" 2>&1 | head -4
  echo "## timeline $bf: $((SECONDS - t0)) s"
done
timeout 120 python3 scripts/benchmarks/benchmark.py --targets --device cuda --repeats 3 \
  --no-isolate --no-update-doc --only '^(?!.*(native=0|init=fft|per_point=0))' \
  --out "$OUT/targets-cuda.json" 2>&1 | tail -12
echo "## targets: $((SECONDS - t0)) s"
if [[ -d ${HG:-} ]]; then
  for i in 1 2; do
    s=$(date +%s.%N)
    timeout 90 python3 -m torch_stsdic run "$HG" --subset 31 --step 20 --roi 150 20 1120 734 \
      --m 2 --device cuda --out /tmp/hg.h5 --overwrite --no-progress 2>&1 | tail -4
    echo "## hourglass stsdic run --device cuda, process $i: $(python3 -c \
      "print(round($(date +%s.%N) - $s, 2))") s"
  done
fi
echo "## total: $((SECONDS - t0)) s"
