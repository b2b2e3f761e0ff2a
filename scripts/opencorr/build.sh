#!/usr/bin/env bash
# Build the OpenCorr FFT-CC + IC-GN (1st order) benchmark harness (bench_fftcc_icgn1.cpp, next to this
# script) against an OpenCorr src/ folder, in two variants: bench_native and bench_plain.
#
#   scripts/opencorr/build.sh                                    # the set-up used for docs/bench/opencorr-cpu.json
#   OPENCORR_SRC=~/OpenCorr/src OPENCORR_BUILD=~/oc-build OPENCORR_OPENCV=1 scripts/opencorr/build.sh
#
# Environment (defaults = the set-up the recorded numbers come from):
#   OPENCORR_SRC      OpenCorr src/ folder                     (default /tmp/opencorr/src)
#   OPENCORR_BUILD    output folder for the binaries           (default /tmp/opencorr/build)
#   OPENCORR_DEPS     unpacked Eigen / FFTW wheels             (default /tmp/opencorr/deps)
#   OPENCORR_DL       downloaded wheels                        (default /tmp/opencorr/dl)
#   OPENCORR_DATA     where the PGM images are written         (default /tmp/opencorr/data)
#   OPENCORR_TIFFS    folder holding img000.tif, img001.tif    (default /tmp/stsdic_bench/cli_pair_m0_v1,
#                     written by scripts/benchmarks/bench_cli.py / scripts/benchmarks/bench_opencorr.py); skipped if missing
#   OPENCORR_OPENCV   1: compile and link against OpenCV (pkg-config opencv4), for an unpatched OpenCorr
#                     clone whose oc_image.cpp reads images with cv::imread (default 0: no OpenCV, which
#                     needs the PGM-loader patch of oc_image.{h,cpp} described in README.md)
#
# Where each piece came from for the recorded numbers (nothing from OpenCorr is stored in this repo):
#   $OPENCORR_SRC/*.{h,cpp}      OpenCorr (github.com/vincentjzy/OpenCorr) src/ files, transcribed from a
#                                public code index (no git clone was possible on that machine):
#                                  commit 5f84be6fe5520d92e9eb6a555fe3caf1d10e4a2a: oc_icgn.cpp, oc_fftcc.cpp,
#                                    oc_cubic_bspline.cpp, oc_gradient.cpp, oc_subset.cpp, oc_image.cpp
#                                  commit 500f447d2350d894acf9f9030bb3fbffc5afb9dc: every header used, and
#                                    oc_dic.cpp, oc_deformation.cpp, oc_poi.cpp, oc_point.cpp, oc_array.cpp
#                                (5f84be6 = the commit of examples/ide_configuration; its .cpp differ from
#                                500f447 only by an added '#include <omp.h>'; headers are unchanged there.)
#                                Only 2D code is compiled: the 3D/2nd-order definitions were cut from the .cpp
#                                files (marked "[bench copy] TRIMMED"); oc_image.{h,cpp} is MODIFIED to read
#                                8-bit binary PGM instead of cv::imread + cv::cv2eigen (no OpenCV).
#                                In that set-up the file bodies live in $OPENCORR_SRC/body and the MPL header
#                                in $OPENCORR_SRC/LICENSE_HEADER.txt; this script joins them (a git clone has
#                                no body/ folder and is used as it is).
#   Eigen 3.4.1 headers          PyPI wheel cmeel-eigen 3.4.1  (pip download --no-deps cmeel-eigen)
#   FFTW 3.3.5 single precision  PyPI wheel pyfftw 0.15.1: pyfftw.libs/libfftw3f-b4465a35.so.3.5.5
#                                (built "fftw-3.3.5-sse2-avx"; OpenCorr's Get-started doc names FFTW 3.3.5)
#                                and libfftw3-6b983104.so.3.5.5 (double; fftw_malloc/fftw_free)
#   fftw3.h                      PyPI wheel pylib-fftw3f 0.0.5 (FFTW 3.3.10 header; same API)
#   images                       $OPENCORR_TIFFS/img00{0,1}.tif -> 8-bit binary PGM (Python, tifffile)
set -euo pipefail

SRC=${OPENCORR_SRC:-/tmp/opencorr/src}
BUILD=${OPENCORR_BUILD:-/tmp/opencorr/build}
DEPS=${OPENCORR_DEPS:-/tmp/opencorr/deps}
DL=${OPENCORR_DL:-/tmp/opencorr/dl}
DATA=${OPENCORR_DATA:-/tmp/opencorr/data}
TIFFS=${OPENCORR_TIFFS:-/tmp/stsdic_bench/cli_pair_m0_v1}
OPENCV=${OPENCORR_OPENCV:-0}
HERE="$(cd "$(dirname "$0")" && pwd)"
test -d "$SRC" || { echo "OpenCorr src folder not found: $SRC (set OPENCORR_SRC)"; exit 1; }
mkdir -p "$DL" "$DEPS" "$BUILD" "$DATA"

# --- dependencies (PyPI wheels) ---
if [ ! -d "$DEPS/eigen/cmeel.prefix/include/eigen3/Eigen" ]; then
  (cd "$DL" && pip download --no-deps cmeel-eigen==3.4.1)
  unzip -q -o "$DL"/cmeel_eigen-3.4.1-*.whl -d "$DEPS/eigen"
fi
if [ ! -d "$DEPS/pyfftw/pyfftw.libs" ]; then
  (cd "$DL" && pip download --no-deps pyfftw==0.15.1)
  unzip -q -o "$DL"/pyfftw-0.15.1-*.whl -d "$DEPS/pyfftw"
fi
if [ ! -f "$DEPS/fftw3f/pylib_fftw3f/include/fftw3.h" ]; then
  (cd "$DL" && pip download --no-deps pylib-fftw3f==0.0.5)
  unzip -q -o "$DL"/pylib_fftw3f-0.0.5-*.whl -d "$DEPS/fftw3f"
fi
mkdir -p "$DEPS/fftw/include" "$DEPS/fftw/lib"
cp -f "$DEPS/fftw3f/pylib_fftw3f/include/fftw3.h" "$DEPS/fftw/include/"
FFTW_SO=$(ls "$DEPS"/pyfftw/pyfftw.libs/libfftw3f-*.so.3.5.5 | grep -v _omp | head -1)
ln -sf "$FFTW_SO" "$DEPS/fftw/lib/libfftw3f.so"
# OpenCorr's FFTCC allocates its buffers with fftw_malloc/fftw_free (double-precision library), so libfftw3
# is needed too (OpenCorr's own builds link fftw3, fftw3f and fftw3l).
FFTW_D_SO=$(ls "$DEPS"/pyfftw/pyfftw.libs/libfftw3-*.so.3.5.5 | head -1)
ln -sf "$FFTW_D_SO" "$DEPS/fftw/lib/libfftw3.so"

# --- OpenCorr sources: in the transcribed set-up, join the MPL header and each body ---
if [ -d "$SRC/body" ]; then
  for f in "$SRC"/body/*; do cat "$SRC/LICENSE_HEADER.txt" "$f" > "$SRC/$(basename "$f")"; done
fi

# --- images: TIFF -> 8-bit binary PGM (scripts/benchmarks/bench_opencorr.py does the same if they are missing) ---
if [ -f "$TIFFS/img000.tif" ]; then
  TIFFS="$TIFFS" DATA="$DATA" python3 - <<'EOF'
import os

import tifffile

for n in ['img000', 'img001']:
    a = tifffile.imread(os.path.join(os.environ['TIFFS'], n + '.tif'))
    assert a.dtype.name == 'uint8' and a.ndim == 2
    with open(os.path.join(os.environ['DATA'], n + '.pgm'), 'wb') as f:
        f.write(b'P5\n%d %d\n255\n' % (a.shape[1], a.shape[0]))
        f.write(a.tobytes())
EOF
else
  echo "note: $TIFFS/img000.tif not found, PGM images not written (bench_opencorr.py writes them)"
fi

# --- compile ---
# OpenCorr's own macOS build task (examples/ide_configuration/tasks.json) uses: -std=c++14 -O3 -fopenmp (-g).
# bench_native adds -march=native -DNDEBUG; bench_plain is OpenCorr's flags minus -g.
SRCS="oc_array.cpp oc_point.cpp oc_poi.cpp oc_deformation.cpp oc_image.cpp oc_subset.cpp oc_dic.cpp \
      oc_gradient.cpp oc_cubic_bspline.cpp oc_fftcc.cpp oc_icgn.cpp"
INC="-I$SRC -I$DEPS/eigen/cmeel.prefix/include/eigen3/Eigen -I$DEPS/eigen/cmeel.prefix/include/eigen3 -I$DEPS/fftw/include"
LIBS="-L$DEPS/fftw/lib -Wl,-rpath,$DEPS/pyfftw/pyfftw.libs -lfftw3f -lfftw3 -lm"
if [ "$OPENCV" = 1 ]; then
  INC="$INC $(pkg-config --cflags opencv4)"
  LIBS="$LIBS $(pkg-config --libs opencv4)"
fi
build() {  # $1 = output name, rest = flags
  local out=$1; shift
  local objs=""
  mkdir -p "$BUILD/$out.o"
  for s in $SRCS; do
    g++ "$@" $INC -c "$SRC/$s" -o "$BUILD/$out.o/${s%.cpp}.o"
    objs="$objs $BUILD/$out.o/${s%.cpp}.o"
  done
  g++ "$@" $INC -c "$HERE/bench_fftcc_icgn1.cpp" -o "$BUILD/$out.o/bench.o"
  g++ "$@" -o "$BUILD/$out" "$BUILD/$out.o/bench.o" $objs $LIBS
  echo "built $BUILD/$out with: $*"
}
build bench_native -std=c++14 -O3 -march=native -fopenmp -DNDEBUG
build bench_plain  -std=c++14 -O3 -fopenmp
