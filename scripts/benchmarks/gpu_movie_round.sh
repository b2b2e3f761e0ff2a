#!/usr/bin/env bash
# The long-movie records on a lent GPU in one short call (about 4.5 minutes on an H200): the
# CUDA tests, the 500-frame movie with the template made from the series (the default) and
# against frame 0 alone, where the template's time goes, a timeline of the blocks' own work,
# and one `stsdic run --device cuda` of the hourglass.
#
#   HG=.gpu/hourglass bash scripts/benchmarks/gpu_movie_round.sh   # logs and records in $OUT
#
# Needs kornia's wheels in .whl/ (README: GPU) and, for the hourglass, its images in $HG.
set -uo pipefail
OUT=${OUT:-$PWD/gpu-out}
mkdir -p "$OUT"
export OUT PYTHONUNBUFFERED=1 OMP_WAIT_POLICY=PASSIVE STSDIC_GAP_LOG=$OUT/gaps.txt
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
  --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD STSDIC_BENCH_CACHE=${STSDIC_BENCH_CACHE:-$PWD/.benchcache}
mkdir -p "$STSDIC_BENCH_CACHE"
t0=$SECONDS
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
timeout 100 python3 -m pytest -q -p no:cacheprovider tests/test_cuda.py 2>&1 | tail -6
echo "## tests: $((SECONDS - t0)) s"
for sr in "" "--movie-single-reference"; do
  timeout 90 python3 scripts/benchmarks/benchmark.py --movie --device cuda --movie-frames 500 \
    --no-update-doc $sr --out "$OUT/movie-cuda${sr:+-single}.json" 2>&1 | grep -E "^movie|Error"
  echo "## movie $sr: $((SECONDS - t0)) s"
done
timeout 60 python3 scripts/benchmarks/template_parts.py --frames 500 --points 10000 \
  --device cuda --out "$OUT/template-cuda.json" 2>&1 | tail -2
echo "## template: $((SECONDS - t0)) s"
timeout 120 python3 scripts/benchmarks/gpu_timeline.py --frames 60 --single-reference \
  --out "$OUT/timeline.txt" 2>&1 | head -3  # its profile part: 60 s were too few for 120
echo "## timeline: $((SECONDS - t0)) s"
if [[ -d ${HG:-} ]]; then
  s=$(date +%s.%N)
  timeout 60 python3 -m torch_stsdic run "$HG" --subset 31 --step 20 --roi 150 20 1120 734 \
    --m 2 --device cuda --out /tmp/hg.h5 --overwrite --no-progress 2>&1 | tail -4
  echo "## hourglass stsdic run --device cuda: $(python3 -c \
    "print(round($(date +%s.%N) - $s, 2))") s"
fi
echo "## total: $((SECONDS - t0)) s"
