#!/usr/bin/env bash
# Issue 45's GPU round in one call (about 8 minutes on an H200): the CUDA tests (the whole-stage
# Triton solver's among them), the solver at 38,809 and 250,000 POIs (Triton solver and the
# batched loop), the 500-frame movie with defaults and against frame 0 alone, and the hourglass
# with `stsdic run --device cuda` split by pass and kind of work (run_parts.py, with the
# classical baseline). `gpu_round.sh timeline` adds the device's busy share and the syncs;
# `choices` times the hourglass with the GPU's choices against the CPU's (device_choices.py:
# masked solves against reads, and whether the files are the same to the bit); `budget` whether
# a run given --memory-mb keeps to it on the device (gpu_budget.py: peak allocations); `compact`
# the 500-frame movie against frame 0 alone without a block's masked solves taken to a learned
# size (TORCH_STSDIC_CHOICES=COMPACT_ROWS=0), without a reading block's taken at their count
# (COMPACT_READING=0), then the GPU's own choices: the A/B of docs/benchmarks.md "Masked
# solves taken to a learned size", about 3 x 50 s).
#
#   HG=.gpu/hourglass bash scripts/benchmarks/gpu_round.sh [steps]   # logs and records in $OUT
#                                      # steps: tests,solver,movie,parts,timeline,syncs,choices,budget,compact
#
# Needs kornia's wheels in .whl/ (README: GPU) and, for the hourglass, its images in $HG.
set -uo pipefail
OUT=${OUT:-$PWD/gpu-out}
mkdir -p "$OUT"
STEPS=${1:-tests,solver,movie,parts}
export OUT PYTHONUNBUFFERED=1 OMP_WAIT_POLICY=PASSIVE STSDIC_GAP_LOG=$OUT/gaps.txt
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl || exit 1
fi
export PYTHONPATH=/tmp/site:$PWD STSDIC_BENCH_CACHE=${STSDIC_BENCH_CACHE:-$PWD/.benchcache}
mkdir -p "$STSDIC_BENCH_CACHE"
step() { [[ ",$STEPS," == *",$1,"* ]]; }
log() { echo "$*" | tee -a "$OUT/log.txt"; }
t0=$SECONDS
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee -a "$OUT/log.txt"
python3 -c "import torch, triton, kornia, sys; print(sys.version.split()[0], torch.__version__,
triton.__version__, kornia.__version__)" | tee -a "$OUT/log.txt"
git log -1 --format='code %h %s' 2>/dev/null | cut -c1-80 | tee -a "$OUT/log.txt"
if step tests; then
  timeout ${TESTS_S:-150} python3 -m pytest -q -p no:cacheprovider --maxfail=6 \
    tests/test_triton_solve.py tests/test_cuda.py tests/test_triton.py \
    tests/test_mixed_windows.py tests/test_row_writer.py tests/test_frames.py 2>&1 \
    | tee "$OUT/tests.txt" | tail -25
  log "## tests: $((SECONDS - t0)) s"
fi
if step solver; then
  timeout ${SOLVER_S:-100} python3 scripts/benchmarks/benchmark.py --targets --device cuda --repeats 3 \
    --no-isolate --no-update-doc \
    --only '^solve .*N~(38809|250000) float32 cuda( step5)?( per_point=0)? [0-9]+t$' \
    --out "$OUT/solver-cuda.json" 2>&1 | tee -a "$OUT/log.txt" | tail -12
  log "## solver: $((SECONDS - t0)) s"
fi
if step movie; then
  for sr in "" "--movie-single-reference"; do
    timeout ${MOVIE_S:-120} python3 scripts/benchmarks/benchmark.py --movie --device cuda \
      --movie-frames 500 --no-update-doc $sr --out "$OUT/movie-cuda${sr:+-single}.json" 2>&1 \
      | tee -a "$OUT/log.txt" | grep -E "^movie|Error|error" | cut -c1-300
    log "## movie $sr: $((SECONDS - t0)) s"
  done
fi
if step parts && [[ -d ${HG:-} ]]; then
  timeout ${PARTS_S:-90} python3 scripts/benchmarks/run_parts.py --baseline --repeats ${PARTS_REPEATS:-1} \
    --out "$OUT/parts-hourglass-cuda.json" -- "$HG" --roi 150 20 1120 734 --subset 31 --step 20 \
    --device cuda 2>&1 | tee -a "$OUT/log.txt" | tail -30
  log "## parts: $((SECONDS - t0)) s"
fi
if step timeline; then
  timeout ${TIMELINE_S:-70} python3 scripts/benchmarks/gpu_timeline.py --frames 60 --single-reference \
    --out "$OUT/timeline.txt" 2>&1 | head -14
  log "## timeline: $((SECONDS - t0)) s"
fi
if step syncs && [[ -d ${HG:-} ]]; then
  timeout ${SYNCS_S:-60} python3 scripts/benchmarks/count_syncs.py --out "$OUT/syncs-hourglass-cuda.json" \
    -- "$HG" --roi 150 20 1120 734 --subset 31 --step 20 --device cuda 2>&1 | tail -8
  log "## syncs: $((SECONDS - t0)) s"
fi
if step choices && [[ -d ${HG:-} ]]; then
  timeout ${CHOICES_S:-150} python3 scripts/benchmarks/device_choices.py --rounds ${CHOICES_ROUNDS:-2} \
    --out "$OUT/device-choices-hourglass-cuda.json" -- "$HG" --roi 150 20 1120 734 --subset 31 \
    --step 20 --device cuda 2>&1 | tee -a "$OUT/log.txt" | tail -9
  log "## choices: $((SECONDS - t0)) s"
fi
if step budget && [[ -d ${HG:-} ]]; then
  timeout ${BUDGET_S:-120} python3 scripts/benchmarks/gpu_budget.py --device cuda --budgets 256 \
    --out "$OUT/budget-hourglass-cuda.json" -- "$HG" --roi 150 20 1120 734 --subset 31 \
    --step 20 2>&1 | tee -a "$OUT/log.txt" | tail -6
  log "## budget: $((SECONDS - t0)) s"
fi
if step compact; then
  for c in COMPACT_ROWS=0 COMPACT_READING=0 COMPACT_ROWS=1; do
    TORCH_STSDIC_CHOICES="$c" timeout ${MOVIE_S:-120} python3 scripts/benchmarks/benchmark.py \
      --movie --device cuda --movie-frames 500 --no-update-doc --movie-single-reference \
      --out "$OUT/movie-cuda-single-${c/=/}.json" 2>&1 \
      | tee -a "$OUT/log.txt" | grep -E "^movie|Error|error" | cut -c1-300
    log "## compact $c: $((SECONDS - t0)) s"
  done
fi
log "## total: $((SECONDS - t0)) s"
