#!/usr/bin/env bash
# GPU correctness and speed in one call (a lent GPU machine with torch, Triton, h5py and
# tifffile; kornia travels as wheels in .whl/, the benchmark inputs in .benchcache/).
#
#   bash scripts/benchmarks/gpu_check.sh [steps]   # steps: any of tests,kernels,targets,cli,
#                                                  # cli2,movie,profile,movie32,warm,solver
#
# Writes its logs and JSON records under $OUT (default ./gpu-out). Each step has its own
# time limit, so one that hangs cannot take the others with it.
set -uo pipefail
OUT=${OUT:-$PWD/gpu-out}
mkdir -p "$OUT"
STEPS=${1:-tests,kernels,targets,cli,movie}
export PYTHONUNBUFFERED=1 OMP_WAIT_POLICY=PASSIVE
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site:$PWD
else
  export PYTHONPATH=$PWD
fi
export STSDIC_BENCH_CACHE=${STSDIC_BENCH_CACHE:-$PWD/.benchcache}
mkdir -p "$STSDIC_BENCH_CACHE"
nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm --format=csv | tee -a "$OUT/log.txt"
python3 -c "import torch, triton, kornia, sys; print(sys.version.split()[0], torch.__version__,
triton.__version__, kornia.__version__, torch.cuda.get_device_name(0))" | tee -a "$OUT/log.txt"
t0=$SECONDS
step() { [[ ",$STEPS," == *",$1,"* ]]; }
if step tests; then
  timeout 150 python3 -m pytest -q -p no:cacheprovider --maxfail=8 \
    ${TESTS:-tests/test_cuda.py tests/test_triton.py tests/test_triton_solve.py tests/test_frames.py} 2>&1 | tee -a "$OUT/log.txt" | tail -40
  echo "## tests: $((SECONDS - t0)) s"
fi
if step kernels; then
  timeout 50 python3 scripts/benchmarks/bench_kernels.py --device cuda --out "$OUT/kernels-cuda.json" \
    2>&1 | tee -a "$OUT/log.txt" | tail -15
  echo "## kernels: $((SECONDS - t0)) s"
fi
if step targets; then
  timeout 130 python3 scripts/benchmarks/benchmark.py --targets --device cuda --repeats 3 --no-isolate \
    --no-update-doc --only '^(?!.*(native=0|init=fft|per_point=0))' --out "$OUT/targets-cuda.json" \
    2>&1 | tee -a "$OUT/log.txt" | tail -25
  echo "## targets: $((SECONDS - t0)) s"
fi
if step cli; then
  timeout 120 python3 scripts/benchmarks/bench_cli.py --device cuda --repeats ${CLI_REPEATS:-3} --threads 4 \
    --out "$OUT/cli-cuda.json" 2>&1 | tee -a "$OUT/log.txt" | tail -14
  echo "## cli: $((SECONDS - t0)) s"
fi
if step cli2; then  # the same with STS(5) (--m 2): the shared-motion pass, its sample guess,
  # the model check
  timeout 120 python3 scripts/benchmarks/bench_cli.py --m 2 --device cuda --repeats ${CLI_REPEATS:-3} \
    --threads 4 --out "$OUT/cli-cuda-m2.json" 2>&1 | tee -a "$OUT/log.txt" | tail -14
  echo "## cli2: $((SECONDS - t0)) s"
fi
if step movie; then
  timeout 120 python3 scripts/benchmarks/benchmark.py --movie --device cuda --movie-frames "${MOVIE_FRAMES:-500}" \
    --no-update-doc --out "$OUT/movie-cuda.json" 2>&1 | tee -a "$OUT/log.txt" | tail -12
  echo "## movie: $((SECONDS - t0)) s"
fi
if step profile; then  # one `stsdic run --device cuda` of the benchmark pair, by function
  read -r DIR CSV < <(python3 -c "import sys; sys.path.insert(0, 'scripts/benchmarks'); import bench_cli as b
d, c, _ = b.ensure_data(0); print(d, c)")
  for i in 1 2; do
    s0=$(date +%s.%N)
    timeout 60 python3 -m torch_stsdic run "$DIR" --points "$CSV" --subset 21 --m 0 \
      --out /tmp/r.h5 --overwrite --no-progress --device cuda 2>&1 | tail -3 | tee -a "$OUT/log.txt"
    echo "## stsdic run --device cuda, process: $(python3 -c "print(round($(date +%s.%N) - $s0, 2))") s" \
      | tee -a "$OUT/log.txt"
  done
  timeout 60 python3 -m cProfile -s cumtime -m torch_stsdic run "$DIR" --points "$CSV" --subset 21 \
    --m 0 --out /tmp/r.h5 --overwrite --no-progress --device cuda 2>&1 | head -70 \
    | tee -a "$OUT/log.txt" | cut -c1-150 | head -45
  echo "## profile: $((SECONDS - t0)) s"
fi
if step movie32; then  # the long movie with 32 target frames a block instead of the default
  timeout 150 python3 scripts/benchmarks/benchmark.py --movie --device cuda --movie-frames "${MOVIE_FRAMES:-500}" \
    --movie-batch-frames 32 --no-update-doc --out "$OUT/movie-cuda-b32.json" 2>&1 \
    | tee -a "$OUT/log.txt" | tail -5
  echo "## movie32: $((SECONDS - t0)) s"
fi
if step warm; then  # stsdic run --device cuda twice in one process: first-use cost vs the rest
  timeout 120 python3 - <<'PY' 2>&1 | tee -a "$OUT/log.txt"
import contextlib, io, sys, time
sys.path.insert(0, "scripts/benchmarks")
import bench_cli as b
from torch_stsdic.cli import main
d, c, _ = b.ensure_data(0)
for dev in ("cuda", "cuda", "cuda"):
    t = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):
        rc = main(["run", str(d), "--points", str(c), "--subset", "21", "--m", "0", "--out",
                   "/tmp/w.h5", "--overwrite", "--no-progress", "--device", dev])
    print(f"## stsdic run --device {dev} in one process: {time.perf_counter() - t:.3f} s (rc {rc})")
PY
  echo "## warm: $((SECONDS - t0)) s"
fi
if step solver; then  # the whole-stage Triton solver (kernels/triton_solve.py) against the
  # batched loop (per_point=0: a Triton right-hand side and torch ops per iteration), classical
  # and STS(5) at 38,809 and 250,000 POIs (~2 min); then its tests on the GPU
  timeout 240 python3 scripts/benchmarks/benchmark.py --targets --device cuda --repeats 3 --no-isolate \
    --no-update-doc --only '^solve .*N~(38809|250000) float32 cuda( step5)?( per_point=0)? [0-9]+t$' \
    --out "$OUT/solver-cuda.json" 2>&1 | tee -a "$OUT/log.txt" | tail -14
  echo "## solver: $((SECONDS - t0)) s"
  timeout 120 python3 -m pytest -q -p no:cacheprovider tests/test_triton_solve.py 2>&1 \
    | tee -a "$OUT/log.txt" | tail -8
  echo "## solver tests: $((SECONDS - t0)) s"
fi
