#!/usr/bin/env bash
# scripts/gpu_check.sh: build and test scandyn on the GPU machine, offline.
#
#   scripts/gpu_check.sh [OUTDIR]        (default: $OUT)
#
# Run from anywhere on the GPU machine after scripts/prepare_device.sh was run on
# a networked machine and .deps/root travelled with the tree. Steps:
#   1. environment report (GPU, driver, nvcc, compilers)          -> env.txt
#   2. configure: Release, CUDA on (sm_90 unless CMAKE_CUDA_ARCHITECTURES is set
#      in the environment), -march=native, every kernel variant
#      (SCANDYN_SIM_EFFECT_SETS, SCANDYN_BENCH_VARIANTS, SCANDYN_HOST_EFFECT_SETS and SCANDYN_CUDA_ALL_CAPACITIES on, whatever an earlier
#      configure of the build directory said), urdfdom from .deps/root -> configure.log
#   3. build                                                        -> build.log
#   4. ctest (every test; CUDA tests must not be skipped here)      -> ctest.log, ctest.xml
#   5. compute-sanitizer --tool memcheck on every test_cuda_* binary -> sanitizer/<name>.log
#   5b. scripts/accuracy_report --full --name accuracy-gpu, when numpy is
#       importable (plots where matplotlib is too) -> accuracy-gpu.tar.gz (its
#       accuracy-gpu.md and accuracy-gpu/ go to docs/) and accuracy-gpu.md
#   6. every bench/bench_* program, JSON results                    -> bench/<name>.json
#      (bench_cuda_chain_fd's hybrid timeline also                    -> hybrid-timeline-rope1e6.csv;
#      the hybrid's host part, bench/chain_carries_cost, 1..16 threads -> chain_carries_cost.csv)
#   7. with two or more GPUs: scripts/multi_gpu_check.sh (the sharded engines' and
#      simulator's tests, one GPU against all of them in one process, the Python
#      examples under torchrun and mpirun)                            -> multi_gpu/
#   summary.txt lists each step's outcome; the exit status is non-zero if any failed.
# A failed configure or build stops the run; later steps run even if an earlier
# test step failed.
#
# Environment: SCANDYN_GPU_BUILD_DIR (default build-gpu), CMAKE_CUDA_ARCHITECTURES
# (default 90), SCANDYN_JOBS (default nproc), SCANDYN_SKIP_SANITIZER=1,
# SCANDYN_SKIP_TESTS=1 (no ctest, no compute-sanitizer), SCANDYN_BUILD_TARGETS (build
# only these targets, e.g. "bench_cuda_id bench_cuda_fd"), SCANDYN_SANITIZER_FILTER (gtest filter under memcheck; default leaves out the
# 10^5..10^6-link cases, which repeat the smaller ones' kernels at 10-100x the
# time), SCANDYN_SKIP_ACCURACY=1, SCANDYN_SKIP_BENCH=1, SCANDYN_BENCH_ONLY (a regex of bench program names),
# SCANDYN_BENCH_ARGS (extra Google Benchmark flags, e.g.
# --benchmark_min_time=0.05s), SCANDYN_BENCH_TIMEOUT (seconds per program, default 300),
# SCANDYN_VARIANTS=OFF (configure without the fused-step and host-step effect sets and the bench
# variants: a faster build), SCANDYN_CTEST_REGEX (ctest -R: only these tests, for a
# build of some targets), SCANDYN_ACCURACY_ARGS (extra accuracy_report flags, e.g.
# "--backends cuda"), SCANDYN_FD_CHECK_COST=1 (bench/fd_check_engine_cost on serial,
# openmp and cuda -> fd_check_engine_cost.csv).
set -euo pipefail

cd "$(dirname "${BASH_SOURCE[0]}")/.."
repo=$PWD

die() { echo "gpu_check.sh: error: $*" >&2; exit 2; }
note() { printf '\n==== [%s] %s\n' "$(date +%H:%M:%S)" "$*"; }

out=${1:-${OUT:-}}
[[ -n "$out" ]] || die "no output directory: pass it as \$1 or set \$OUT"
mkdir -p "$out"
out=$(cd "$out" && pwd)
build=${SCANDYN_GPU_BUILD_DIR:-build-gpu}
jobs=${SCANDYN_JOBS:-$(nproc)}
arch=${CMAKE_CUDA_ARCHITECTURES:-90}
summary=$out/summary.txt
: >"$summary"
status=0
record() {  # record STEP RC
  local word=ok
  [[ "$2" == 0 ]] || { word="FAILED (exit $2)"; status=1; }
  printf '%-28s %s\n' "$1" "$word" | tee -a "$summary"
}

# ---- staged dependencies ---------------------------------------------------------
deps=$repo/.deps/root
[[ -d "$deps/usr" ]] ||
  die "$deps is missing: run scripts/prepare_device.sh on a networked machine and bring .deps/root along"
urdfdom_cfg=$(find "$deps/usr/lib" -path '*/urdfdom/cmake/urdfdom-config.cmake' 2>/dev/null | head -n1)
[[ -n "$urdfdom_cfg" ]] || die "no urdfdom CMake config under $deps (re-run prepare_device.sh)"
libdir=$(dirname "$(dirname "$(dirname "$urdfdom_cfg")")")  # .../usr/lib/<multiarch>
if grep -q ';/usr/lib/' "$(dirname "$urdfdom_cfg")/urdfdomExport.cmake"; then
  die "urdfdomExport.cmake under $deps still names /usr/lib files (re-run prepare_device.sh)"
fi
export LD_LIBRARY_PATH=$libdir${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
export CMAKE_PREFIX_PATH=$deps/usr${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}

export SCANDYN_MODELS_DIR=$repo/models  # the shipped robot models

# CUDA tools: PATH first, then the usual toolkit location
if ! command -v nvcc >/dev/null 2>&1 && [[ -x /usr/local/cuda/bin/nvcc ]]; then
  export PATH=/usr/local/cuda/bin:$PATH
fi
command -v nvcc >/dev/null 2>&1 || die "nvcc not found (PATH, /usr/local/cuda/bin)"
sanitizer=$(command -v compute-sanitizer 2>/dev/null || true)
for c in "$(dirname "$(command -v nvcc)")/compute-sanitizer" \
         "$(dirname "$(dirname "$(command -v nvcc)")")/compute-sanitizer/compute-sanitizer"; do
  [[ -n "$sanitizer" ]] && break
  [[ -x "$c" ]] && sanitizer=$c
done

# ---- 1. environment ------------------------------------------------------------
note "environment -> $out/env.txt"
{
  echo "date: $(date -u +%Y-%m-%dT%H:%M:%SZ)"
  echo "host: $(uname -srm), $(nproc) cores"
  [[ -r /etc/os-release ]] && (. /etc/os-release && echo "os: $PRETTY_NAME")
  echo "commit: $(git -C "$repo" rev-parse --verify -q HEAD 2>/dev/null || echo 'unknown (not a git checkout)')"
  echo "nvcc: $(nvcc --version | tail -n2 | paste -sd' ')"
  echo "compute-sanitizer: ${sanitizer:-not found}"
  echo "cmake: $(cmake --version | head -n1)"
  echo "c++: $(c++ --version | head -n1)"
  echo "CMAKE_PREFIX_PATH=$CMAKE_PREFIX_PATH"
  echo "LD_LIBRARY_PATH=$LD_LIBRARY_PATH"
  echo "SCANDYN_MODELS_DIR=$SCANDYN_MODELS_DIR"
  echo "staged packages:"
  sed 's/^/  /' "$repo/.deps/manifest.txt" 2>/dev/null || echo "  (no .deps/manifest.txt)"
  echo
  nvidia-smi 2>&1 || echo "nvidia-smi failed or is missing"
} >"$out/env.txt" 2>&1
cat "$out/env.txt"

# ---- 2. configure ----------------------------------------------------------------
note "configure $build (CUDA architectures $arch) -> $out/configure.log"
set +e
cmake -S "$repo" -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=Release \
  -DSCANDYN_CUDA=ON -DCMAKE_CUDA_ARCHITECTURES="$arch" -DSCANDYN_NATIVE=ON \
  -DSCANDYN_SIM_EFFECT_SETS="${SCANDYN_VARIANTS:-ON}" -DSCANDYN_BENCH_VARIANTS="${SCANDYN_VARIANTS:-ON}" \
  -DSCANDYN_HOST_EFFECT_SETS="${SCANDYN_VARIANTS:-ON}" -DSCANDYN_CUDA_ALL_CAPACITIES=ON \
  -DCMAKE_PREFIX_PATH="$deps/usr" -DSCANDYN_MODELS_DIR="$SCANDYN_MODELS_DIR" \
  2>&1 | tee "$out/configure.log"
rc=${PIPESTATUS[0]}
set -e
record configure "$rc"
((rc == 0)) || die "configure failed; see $out/configure.log"
# the urdfdom used must be the staged one
grep -q "urdfdom_DIR:PATH=$deps" "$build/CMakeCache.txt" ||
  die "CMake found urdfdom outside $deps: $(grep urdfdom_DIR "$build/CMakeCache.txt")"

# ---- 3. build ------------------------------------------------------------------
note "build (-j$jobs) -> $out/build.log"
set +e
read -r -a targets <<<"${SCANDYN_BUILD_TARGETS:-}"
cmake --build "$build" --parallel "$jobs" ${targets[@]+--target "${targets[@]}"} 2>&1 | tee "$out/build.log"
rc=${PIPESTATUS[0]}
set -e
record build "$rc"
((rc == 0)) || die "build failed; see $out/build.log"

if [[ "${SCANDYN_SKIP_TESTS:-0}" == 1 ]]; then
  note "ctest and compute-sanitizer skipped (SCANDYN_SKIP_TESTS=1)"
else
# ---- 4. tests ------------------------------------------------------------------
note "ctest -> $out/ctest.log"
junit=()
ctest_version=$(ctest --version | awk 'NR == 1 {print $3}')
if [[ "$(printf '%s\n' 3.21 "$ctest_version" | sort -V | head -n1)" == 3.21 ]]; then
  junit=(--output-junit "$out/ctest.xml")  # CMake >= 3.21
fi
set +e
ctest_only=()
[[ -n "${SCANDYN_CTEST_REGEX:-}" ]] && ctest_only=(-R "$SCANDYN_CTEST_REGEX")
ctest --test-dir "$build" --output-on-failure --parallel "$jobs" ${junit[@]+"${junit[@]}"} \
  ${ctest_only[@]+"${ctest_only[@]}"} \
  2>&1 | tee "$out/ctest.log"
rc=${PIPESTATUS[0]}
set -e
record ctest "$rc"
cp "$build/Testing/Temporary/LastTest.log" "$out/ctest-LastTest.log" 2>/dev/null || true
# On this machine a skipped CUDA test means the device was not usable: a failure.
# (the GPU suites are named Cuda*; Cli.* tests of the no-device errors skip here)
skipped=$(grep -E 'Not Run|Skipped' "$out/ctest.log" | grep -E 'Test +#[0-9]+: Cuda' || true)
if [[ -n "$skipped" ]]; then
  echo "$skipped"
  record "cuda tests not skipped" 1
else
  record "cuda tests not skipped" 0
fi

# ---- 5. compute-sanitizer ------------------------------------------------------
mapfile -t cuda_tests < <(find "$build/tests" -maxdepth 1 -type f -name 'test_cuda_*' -perm -u+x | sort)
if [[ "${SCANDYN_SKIP_SANITIZER:-0}" == 1 ]]; then
  note "compute-sanitizer skipped (SCANDYN_SKIP_SANITIZER=1)"
elif [[ -z "$sanitizer" ]]; then
  note "compute-sanitizer not found"
  record "compute-sanitizer" 127
elif ((${#cuda_tests[@]} == 0)); then
  note "no test_cuda_* programs were built"
  record "compute-sanitizer" 1
else
  mkdir -p "$out/sanitizer"
  for t in "${cuda_tests[@]}"; do
    name=$(basename "$t")
    note "compute-sanitizer memcheck $name -> $out/sanitizer/$name.log"
    set +e
    "$sanitizer" --tool memcheck --leak-check full --error-exitcode 86 "$t" \
      --gtest_filter="${SCANDYN_SANITIZER_FILTER:--*LongRopes*:*BatchesOfRopes*}" \
      2>&1 | tee "$out/sanitizer/$name.log"
    rc=${PIPESTATUS[0]}
    set -e
    record "memcheck $name" "$rc"
  done
fi
fi

# ---- 5b. accuracy report (full mode), when numpy is importable -----------------
# (matplotlib draws its plots where it is importable; without it the report has its
# tables and CSVs only.) It is written into $build/accuracy, kept there: the full mode
# takes ~25 minutes on an H200 machine, so where one command may run 10 minutes at
# most, run this step again with SCANDYN_ACCURACY_ARGS=--resume (and
# SCANDYN_SKIP_TESTS=1 SCANDYN_SKIP_BENCH=1) on the same build directory until it
# finishes; the rows measured so far also go back as accuracy-partial.jsonl. The
# finished report goes back as one archive (the device tool returns few files):
# accuracy-gpu.tar.gz, unpacked into docs/ it gives docs/accuracy-gpu.md and
# docs/accuracy-gpu/; accuracy-gpu.md also lies beside it.
py=.venv/bin/python
[[ -x "$py" ]] || py=python3
if [[ "${SCANDYN_SKIP_ACCURACY:-0}" == 1 ]]; then
  note "accuracy report skipped (SCANDYN_SKIP_ACCURACY=1)"
elif "$py" -c 'import numpy' 2>/dev/null; then
  acc=$build/accuracy
  note "accuracy report (full) in $acc -> $out/accuracy-gpu.tar.gz (accuracy-gpu.md, accuracy-gpu/: unpack into docs/)"
  set +e
  read -r -a accuracy_args <<<"${SCANDYN_ACCURACY_ARGS:-}"
  "$py" scripts/accuracy_report --full --name accuracy-gpu --out-dir "$acc" --scandyn "$build/scandyn" \
    --stability-test "$build/tests/test_stability" ${accuracy_args[@]+"${accuracy_args[@]}"} \
    --machine "$(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -1), host $(nproc) cores" \
    2>&1 | tee "$out/accuracy.log"
  rc=${PIPESTATUS[0]}
  if [[ -f "$acc/accuracy-gpu/sweep.partial.jsonl" ]]; then  # not finished: resume it
    cp "$acc/accuracy-gpu/sweep.partial.jsonl" "$out/accuracy-partial.jsonl"
  elif [[ -f "$acc/accuracy-gpu.md" ]]; then
    tar -czf "$out/accuracy-gpu.tar.gz" -C "$acc" accuracy-gpu.md accuracy-gpu && cp "$acc/accuracy-gpu.md" "$out/"
  fi
  set -e
  record "accuracy report (full)" "$rc"
else
  note "accuracy report skipped: no numpy for $py (scripts/setup_python.sh; or run scripts/accuracy_report --full later)"
fi

# ---- 5c. the forward-dynamics check's cost per engine ---------------------------
if [[ "${SCANDYN_FD_CHECK_COST:-0}" == 1 ]]; then
  note "fd_check_engine_cost (serial, openmp, cuda) -> $out/fd_check_engine_cost.csv"
  set +e
  timeout "${SCANDYN_BENCH_TIMEOUT:-300}" "$build/bench/fd_check_engine_cost" --min-time 0.1 \
    --backend serial,openmp,cuda --out "$out/fd_check_engine_cost.csv" 2>&1 | tee "$out/fd_check_engine_cost.log"
  rc=${PIPESTATUS[0]}
  set -e
  record "fd_check_engine_cost" "$rc"
fi

# ---- 6. benchmarks -------------------------------------------------------------
mapfile -t benches < <(find "$build/bench" -maxdepth 1 -type f -name 'bench_*' -perm -u+x 2>/dev/null | sort |
  grep -E "${SCANDYN_BENCH_ONLY:-.}" || true)
if [[ "${SCANDYN_SKIP_BENCH:-0}" == 1 ]]; then
  note "benchmarks skipped (SCANDYN_SKIP_BENCH=1)"
elif ((${#benches[@]} == 0)); then
  note "no bench_* programs were built"
else
  mkdir -p "$out/bench"
  read -r -a bench_args <<<"${SCANDYN_BENCH_ARGS:-}"
  for b in "${benches[@]}"; do
    name=$(basename "$b")
    note "$name -> $out/bench/$name.json"
    set +e
    timeout "${SCANDYN_BENCH_TIMEOUT:-300}" "$b" --benchmark_out="$out/bench/$name.json" \
      --benchmark_out_format=json ${bench_args[@]+"${bench_args[@]}"} 2>&1 |
      tee "$out/bench/$name.log"
    rc=${PIPESTATUS[0]}
    set -e
    record "bench $name" "$rc"
    # the hybrid's busy intervals (rope:10^6, float and double) as a CSV for
    # scripts/chain_fd_report.py --timeline
    if [[ "$name" == bench_cuda_chain_fd ]] && grep -q '^timeline,' "$out/bench/$name.log"; then
      { echo "precision,lane,event,c_lo,c_hi,start_ms,end_ms"
        grep '^timeline,' "$out/bench/$name.log" | grep -v '^timeline,precision,' | cut -d, -f2-; } \
        >"$out/hybrid-timeline-rope1e6.csv"
      note "hybrid timeline -> $out/hybrid-timeline-rope1e6.csv"
    fi
  done
fi
# the hybrid's host part on this machine's cores (1 .. 16 threads), interleaved
if [[ "${SCANDYN_SKIP_BENCH:-0}" != 1 && -x "$build/bench/chain_carries_cost" ]]; then
  note "chain_carries_cost -> $out/chain_carries_cost.csv"
  set +e
  OMP_WAIT_POLICY=passive timeout "${SCANDYN_BENCH_TIMEOUT:-300}" "$build/bench/chain_carries_cost" --rounds 7 \
    --threads 2,4,8,16 --estimate 32 >"$out/chain_carries_cost.csv"
  rc=$?
  set -e
  record "chain_carries_cost" "$rc"
fi

# ---- 7. several GPUs in one process, when the machine has them ---------------------
gpus=$(nvidia-smi -L 2>/dev/null | grep -c '^GPU' || true)
if [[ "${SCANDYN_SKIP_BENCH:-0}" != 1 && "${gpus:-0}" -ge 2 && -x "$build/scandyn" ]]; then
  note "multi_gpu_check.sh ($gpus GPUs) -> $out/multi_gpu/"
  set +e
  scripts/multi_gpu_check.sh "$build" "$out/multi_gpu" 2>&1 | tee "$out/multi_gpu.log"
  rc=${PIPESTATUS[0]}
  set -e
  record "bench multi-gpu" "$rc"
fi

note "summary ($out/summary.txt)"
cat "$summary"
exit "$status"
