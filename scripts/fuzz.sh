#!/usr/bin/env bash
# scripts/fuzz.sh SECONDS [TARGET...]: builds the libFuzzer targets (clang,
# -fsanitize=fuzzer,address,undefined, CPU only, in build-fuzz/) and runs each for
# SECONDS, one after the other: urdf (the URDF loader), scene (the scene parser),
# csv (the states CSV reader); default all three. The corpus starts from
# tests/fuzz/seeds/<target>/ (the hostile-input cases of tests/cli/test_hostile.cpp among them), the shipped
# robots ($SCANDYN_MODELS_DIR, urdf) and scenes/*.json (scene), and grows in
# build-fuzz/corpus/<target>/ across runs.
#
# Prints one summary line per target (executions, coverage, corpus, crashes) and
# writes the full libFuzzer output to build-fuzz/fuzz_<target>.log; a crash, leak,
# timeout (an input taking over 10 s), out-of-memory (2 GiB) or sanitizer report
# saves the input as build-fuzz/artifacts/<target>-* and makes the exit status 1.
# Leaks inside urdfdom itself are suppressed (tests/fuzz/lsan.supp says which and why).
#
# Environment: SCANDYN_FUZZ_BUILD_DIR (default build-fuzz), SCANDYN_JOBS (build
# parallelism, default nproc), SCANDYN_MODELS_DIR.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

secs=${1:?usage: scripts/fuzz.sh SECONDS [urdf|scene|csv ...]}
shift
targets=("$@")
((${#targets[@]})) || targets=(urdf scene csv)
dir=${SCANDYN_FUZZ_BUILD_DIR:-build-fuzz}
jobs=${SCANDYN_JOBS:-$(nproc 2>/dev/null || echo 2)}
models=${SCANDYN_MODELS_DIR:-$PWD/models}

command -v clang++ >/dev/null || { echo "fuzz.sh: clang++ not found (libFuzzer needs clang)" >&2; exit 1; }
cmake -S . -B "$dir" -G Ninja -DCMAKE_CXX_COMPILER=clang++ -DCMAKE_BUILD_TYPE=RelWithDebInfo \
  "-DCMAKE_CXX_FLAGS_RELWITHDEBINFO=-O1 -g1" -DSCANDYN_FUZZ=ON -DSCANDYN_SANITIZE=address,undefined \
  -DSCANDYN_CUDA=OFF -DSCANDYN_BENCH=OFF -DSCANDYN_TESTS=OFF -DSCANDYN_OPENMP=OFF \
  "-DSCANDYN_MODELS_DIR=$models" >/dev/null
cmake --build "$dir" --parallel "$jobs" --target "${targets[@]/#/fuzz_}"

mkdir -p "$dir/artifacts"
status=0
for t in "${targets[@]}"; do
  corpus=$dir/corpus/$t
  mkdir -p "$corpus"
  cp -n tests/fuzz/seeds/"$t"/* "$corpus"/ 2>/dev/null || true
  if [[ $t == urdf ]]; then cp -n "$models"/*.urdf "$corpus"/ 2>/dev/null || true; fi
  if [[ $t == scene ]]; then cp -n scenes/*.json "$corpus"/ 2>/dev/null || true; fi
  log=$dir/fuzz_$t.log
  rc=0
  UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1 ASAN_OPTIONS=detect_leaks=1 \
    LSAN_OPTIONS=suppressions=$PWD/tests/fuzz/lsan.supp \
    "$dir/tests/fuzz/fuzz_$t" -max_total_time="$secs" -timeout=10 -rss_limit_mb=2048 -max_len=65536 \
    -print_final_stats=1 -artifact_prefix="$dir/artifacts/$t-" "$corpus" >"$log" 2>&1 || rc=$?
  execs=$(sed -n 's/^stat::number_of_executed_units: *//p' "$log" | tail -1)
  last=$(grep -E '^#[0-9]+' "$log" | tail -1 || true)
  cov=$(sed -n 's/.* cov: \([0-9]*\).*/\1/p' <<<"$last")
  ft=$(sed -n 's/.* ft: \([0-9]*\).*/\1/p' <<<"$last")
  files=$(ls "$corpus" | wc -l)
  crashes=$(ls "$dir/artifacts" | grep -c "^$t-" || true)
  printf 'fuzz_%s: %ss, %s executions, coverage %s edges (%s features), corpus %s files, crashes %s, exit %s\n' \
    "$t" "$secs" "${execs:-?}" "${cov:-?}" "${ft:-?}" "$files" "$crashes" "$rc"
  if ((rc != 0)) || ((crashes > 0)); then
    status=1
    grep -E 'ERROR|SUMMARY|runtime error|==[0-9]+==' "$log" | head -20 >&2 || true
  fi
done
exit "$status"
