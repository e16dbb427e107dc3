#!/usr/bin/env bash
# scripts/test.sh: the project's test command (what CI runs through .ci/run).
#
#   1. scripts/setup.sh (installs missing Debian packages); scripts/setup_python.sh
#      (.venv with numpy, Pinocchio and matplotlib) in the background, while stage 2
#      builds: only its tests and the report use it
#   2. build/       Ninja, Release, CUDA when nvcc is found; ctest; then the Python
#                   package: the extension module built in build/ (SCANDYN_PYTHON=ON,
#                   target _scandyn) and pytest python/tests (docs/python.md)
#      then scripts/accuracy_report --quick into a temporary directory (when .venv
#      has matplotlib), in the background while stage 3 builds
#   3. build-asan/  AddressSanitizer + UBSan, no CUDA, no benchmarks, -O1 -g1 (line
#                   tables for the reports' stack traces); ctest, less the long
#                   rollouts the release stage runs (asan_long below)
#   4. build-fuzz/  the libFuzzer targets (URDF, scene, CSV; clang, ASan + UBSan; only
#                   the sources they reach: scandyn_parsers in CMakeLists.txt),
#                   each run for SCANDYN_FUZZ_SECONDS (default 10) by scripts/fuzz.sh;
#                   any crash, leak, timeout or sanitizer report fails. Skipped with a
#                   warning when clang++ is missing.
# Both stages run even if the first one's tests fail; the exit status is non-zero
# if anything failed. Each step prints a stamp; the last line gives the total time.
#
# Without a GPU (nvidia-smi -L fails: CI) the CUDA code is compiled but never run,
# so stage 2 compiles fewer variant instantiations of it: SCANDYN_SIM_EFFECT_SETS=OFF
# and SCANDYN_BENCH_VARIANTS=OFF (CMakeLists.txt), to PTX only (no ptxas), and the
# host simulator's steps with every joint effect in (SCANDYN_HOST_EFFECT_SETS=OFF).
# Every kernel template, test and benchmark still compiles; scripts/gpu_check.sh
# builds the full variety as sm_90 code.
#
# Environment: SCANDYN_JOBS (build/test parallelism, default: nproc),
# SCANDYN_BUILD_DIR / SCANDYN_ASAN_BUILD_DIR (default build, build-asan),
# SCANDYN_MODELS_DIR (robot models; default the shipped models/),
# SCANDYN_SKIP_SETUP=1, SCANDYN_SKIP_PYTHON=1 (no .venv: the Pinocchio cross-check
# and the Python package's tests are skipped), SCANDYN_SKIP_ASAN=1, SCANDYN_SKIP_FUZZ=1, SCANDYN_FUZZ_SECONDS.
set -euo pipefail

cd "$(dirname "${BASH_SOURCE[0]}")/.."
jobs=${SCANDYN_JOBS:-$(nproc 2>/dev/null || echo 2)}
build=${SCANDYN_BUILD_DIR:-build}
asan_build=${SCANDYN_ASAN_BUILD_DIR:-build-asan}

stamp() { printf '\n==== [%s] %s\n' "$(date +%H:%M:%S)" "$*"; }
start=$SECONDS
failed=()
# what failed, one line each, repeated at the end (CI shows the log's tail)
failed_tests=()
# the output tails of the failed tests (failure_tail), also repeated at the end
failure_tails=()

if [[ "${SCANDYN_SKIP_SETUP:-0}" != 1 ]]; then
  stamp "setup"
  scripts/setup.sh
fi

# Pinocchio for the independent cross-check test (without it that test is skipped)
# and matplotlib for the accuracy report: set up in the background (mostly pip,
# one core) while the release stage configures and builds; waited for before its
# tests.
python_pid=
report_pid=
python_log=$(mktemp)
report_log=$(mktemp)
# (a background job still running at exit, after an error: stop it)
trap 'for p in $python_pid $report_pid; do kill "$p" 2>/dev/null || true; done
      rm -f "$python_log" "$report_log"' EXIT
if [[ "${SCANDYN_SKIP_PYTHON:-0}" != 1 ]]; then
  stamp "python environment (.venv), in the background"
  scripts/setup_python.sh >"$python_log" 2>&1 &
  python_pid=$!
fi
# wait_job PID_VAR LOG LABEL: wait for the background job whose pid PID_VAR holds (none
# started: status 0), clear PID_VAR, print the job's log; the job's exit status
wait_job() {
  local pid=${!1} rc=0
  [[ -n "$pid" ]] || return 0
  stamp "$3: waiting"
  wait "$pid" || rc=$?
  printf -v "$1" '%s' ''
  cat "$2"
  return "$rc"
}
wait_python() {
  wait_job python_pid "$python_log" "python environment (.venv)" ||
    echo "test.sh: warning: .venv setup failed; pinocchio_crosscheck will be skipped" >&2
}

models=${SCANDYN_MODELS_DIR:-models}
if [[ ! -d "$models" ]]; then
  echo "test.sh: warning: robot models not found at $models" \
       "(set SCANDYN_MODELS_DIR); tests that load them will fail" >&2
fi

# build_stage NAME BUILD_DIR CMAKE_ARGS...
build_stage() {
  local name=$1 dir=$2
  shift 2
  # (set -e does not apply inside a function called from `if`: check each step)
  stamp "$name: configure ($dir)"
  cmake -S . -B "$dir" -G Ninja "$@" || return 1
  stamp "$name: build"
  cmake --build "$dir" --parallel "$jobs" || return 1
}

# test_stage NAME BUILD_DIR [CTEST_ARGS...]
test_stage() {
  local name=$1 dir=$2
  shift 2
  stamp "$name: test"
  local rc=0
  rm -f "$dir/Testing/Temporary/LastTestsFailed.log"  # (a failing run writes it afresh)
  ctest --test-dir "$dir" --output-on-failure --parallel "$jobs" "$@" || rc=1
  show_skips "$dir"
  if ((rc)); then
    local log=$dir/Testing/Temporary/LastTestsFailed.log
    if [[ -s "$log" ]]; then
      while IFS= read -r line; do
        failed_tests+=("$name: ${line#*:}")
        failure_tails+=("$(failure_tail "$dir" "${line#*:}" "$name")")
      done <"$log"
    else
      failed_tests+=("$name: ctest failed without a list of failed tests")
    fi
  fi
  return "$rc"
}

# failure_tail BUILD_DIR TEST STAGE: the last 25 lines of TEST's output and its
# verdict (timeout, exit code, signal), from ctest's LastTest.log. CI shows only the
# log's tail, so these are printed again at the end.
failure_tail() {
  local log=$1/Testing/Temporary/LastTest.log
  printf -- '--- %s: %s (its output, last lines; ctest %s)\n' "$3" "$2" "$log"
  [[ -f "$log" ]] || return 0
  awk -v t="$2" '
    $0 ~ "^[0-9]+/[0-9]+ Test: " && substr($0, index($0, "Test: ") + 6) == t { on = 1; n = 0; next }
    on && /^<end of output>/ { out = 1; next }
    on && out && /^Test (Passed|Failed|Timeout)|Exception|Failed|Timeout|exit code|Signal/ { verdict = verdict $0 "\n" }
    on && out && /^-+$/ && verdict != "" { on = 0; out = 0 }
    on && !out { buf[n++ % 25] = $0 }
    END { s = (n > 25) ? n - 25 : 0; for (i = s; i < n; ++i) print buf[i % 25]; printf "%s", verdict }
  ' "$log"
}

# Prints each skipped GoogleTest case with the reason it gave (ctest only says
# "Skipped"); e.g. CUDA tests on a machine without a GPU.
show_skips() {
  local log=$1/Testing/Temporary/LastTest.log
  [[ -f "$log" ]] || return 0
  awk '/^\[ RUN      \] / { name = $4 }
       /: Skipped$/ { getline why; printf "  skipped %s: %s\n", name, why }' "$log" | sort -u
}

# Without a GPU the CUDA code is compiled but never run: compile the simulator's
# all-effects step kernels only (SCANDYN_SIM_EFFECT_SETS), not the 44 per-effect-set
# ones, and of bench_cuda_fd's kernel variants only the engine's own
# (SCANDYN_BENCH_VARIANTS; CMakeLists.txt): several minutes of nvcc on 2 cores.
# There the kernels are also compiled to PTX only (CMAKE_CUDA_ARCHITECTURES=90-virtual:
# nvcc's front end and code generation, without ptxas's SASS, ~40% of nvcc's time
# on the heaviest files); scripts/gpu_check.sh builds sm_90 code and runs it. And the
# host simulator's steps are compiled with every joint effect in
# (SCANDYN_HOST_EFFECT_SETS=OFF: the same numbers; cpu_fallback/simulator_step.cpp
# alone is 110-140 s of the stage's compile time with all 64 sets), as in the
# sanitizer stage; the per-set instantiations are built and tested where a GPU is
# (gpu_check.sh: every option ON, every test), ZeroCoefficientsEqualAbsentEffects
# checking there that they give the all-effects step's numbers. The
# thread-per-instance kernels are compiled for capacity 8 only
# (SCANDYN_CUDA_ALL_CAPACITIES=OFF: one kernel per capacity of four; nvcc user
# seconds of e.g. kernels/rollout_derivatives.cu 82 -> 25, forward_dynamics.cu 26 -> 13).
variants=()
if ! nvidia-smi -L >/dev/null 2>&1; then
  variants=(-DSCANDYN_SIM_EFFECT_SETS=OFF -DSCANDYN_BENCH_VARIANTS=OFF -DCMAKE_CUDA_ARCHITECTURES=90-virtual
            -DSCANDYN_HOST_EFFECT_SETS=OFF -DSCANDYN_CUDA_ALL_CAPACITIES=OFF)
fi
# (SCANDYN_PYTHON=OFF here: the Python stage below turns it on once .venv is ready)
if build_stage release "$build" -DCMAKE_BUILD_TYPE=Release -DSCANDYN_PYTHON=OFF ${variants[@]+"${variants[@]}"}; then
  wait_python
  # The .venv made in the background brings Pinocchio's C++ headers (the pin wheel's
  # cmeel.prefix); when it came after the configure, configure again so that
  # bench/pinocchio_second_order and its ctest (second derivatives against Pinocchio)
  # are built rather than skipped (~45 s of compilation here).
  if compgen -G ".venv/lib/python3*/site-packages/cmeel.prefix/include/pinocchio" >/dev/null &&
     [[ ! -x "$build/bench/pinocchio_second_order" ]]; then
    stamp "release: configure again for bench/pinocchio_second_order (.venv has Pinocchio's headers now)"
    # (the target list is read whole before grep: `cmake --build --target help | grep -q`
    # under pipefail fails at random when grep exits first and ninja gets SIGPIPE)
    build_targets=
    if cmake -S . -B "$build" >/dev/null && build_targets=$(cmake --build "$build" --target help) &&
       grep -q 'pinocchio_second_order' <<<"$build_targets"; then
      cmake --build "$build" --parallel "$jobs" --target pinocchio_second_order ||
        { failed+=(release); failed_tests+=("release: building bench/pinocchio_second_order failed"); }
    fi
  fi
  test_stage release "$build" || failed+=(release)
  release_built=1
else
  failed+=(release)
  failed_tests+=("release: configure or build failed")
  release_built=0
fi
wait_python

# The Python package (python/, docs/python.md): the extension module scandyn._scandyn
# built in the release tree against its library (a reconfigure with SCANDYN_PYTHON=ON
# and one more target), then pytest on python/tests with the build tree's package
# (<build>/python) and the release scandyn command (bit-identity with `scandyn eval`).
# A missing .venv, a failed build, a failing test and "no tests collected" (pytest's
# exit status 5) all fail the stage.
python_stage() {
  local py=$PWD/.venv/bin/python
  if [[ ! -x "$py" ]] || ! "$py" -c 'import nanobind, numpy, pytest' 2>/dev/null; then
    echo "test.sh: .venv with nanobind, numpy and pytest not found (scripts/setup_python.sh)" >&2
    return 1
  fi
  stamp "python: build the module (SCANDYN_PYTHON=ON, $build)"
  cmake -S . -B "$build" -DSCANDYN_PYTHON=ON "-DPython_EXECUTABLE=$py" >/dev/null || return 1
  cmake --build "$build" --parallel "$jobs" --target _scandyn || return 1
  stamp "python: pytest python/tests"
  local abs_build
  abs_build=$(cd "$build" && pwd)
  PYTHONDONTWRITEBYTECODE=1 PYTHONPATH="$abs_build/python" SCANDYN_CLI="$abs_build/scandyn" \
    "$py" -m pytest -q -rs -p no:cacheprovider python/tests || return 1
}
if [[ "${SCANDYN_SKIP_PYTHON:-0}" == 1 ]]; then
  echo "test.sh: warning: SCANDYN_SKIP_PYTHON=1: the Python package's tests are skipped" >&2
elif [[ "$release_built" == 1 ]]; then
  python_stage || { failed+=(python); failed_tests+=("python: module build or pytest failed (pytest's short test summary above)"); }
else
  failed+=(python)
fi

# The accuracy report in its quick mode (CPU, small sizes), into a temporary
# directory so that the tree stays clean; needs .venv (matplotlib). A failing
# report fails the test command. It runs in the background (one process at a
# time: a core) while the ASan stage builds; nothing there checks timings.
report_dir=
if [[ -x .venv/bin/python ]] && .venv/bin/python -c 'import matplotlib' 2>/dev/null; then
  stamp "accuracy report (quick), in the background"
  report_dir=$(mktemp -d)
  .venv/bin/python scripts/accuracy_report --quick --out-dir "$report_dir" --scandyn "$build/scandyn" \
    --stability-test "$build/tests/test_stability" >"$report_log" 2>&1 &
  report_pid=$!
else
  echo "test.sh: warning: .venv with matplotlib not found; accuracy report skipped" >&2
fi
wait_report() {
  [[ -n "$report_pid" ]] || return 0
  if wait_job report_pid "$report_log" "accuracy report (quick)"; then
    rm -rf "$report_dir"
  else
    echo "test.sh: accuracy report failed (output kept in $report_dir)" >&2
    failed+=(accuracy-report)
    failed_tests+=("accuracy-report: scripts/accuracy_report --quick failed (its output above)")
  fi
}

# Long runs of code that shorter tests also run under the sanitizers: the release
# stage runs them in full; under ASan (10-20x slower) they took 190 of the stage's
# ~340 test-seconds (the 10^5-step variational iiwa alone 92 s).
asan_long='^(SimVariational\.IiwaEnergyBoundedFor1e5Steps|SimVariational\.DoublePendulumEnergyBoundedWhereRk4Drifts'
asan_long+='|SimContactsRope\.Rope200DrapesOverASphere(Double|Float)|FdCheckEngine\.FloatParallelOnRope1e6IsFlaggedPerThreshold'
asan_long+='|FreeSystems\.MomentumAndEnergyConservedByRk4|SimEnergy\.UndampedRope1000SymplecticEulerDriftBelow1e4Over1e4Steps'
asan_long+='|SimLongRollout\.UndampedRope100For1e5StepsKeepsItsEnergy)$'
if [[ "${SCANDYN_SKIP_ASAN:-0}" != 1 ]]; then
  # UBSan reports are fatal (-fno-sanitize-recover=all); show where they happen
  export UBSAN_OPTIONS=${UBSAN_OPTIONS:-print_stacktrace=1}
  # -O1 -g1 instead of RelWithDebInfo's -O2 -g (NDEBUG as there): line tables are
  # what the reports' stack traces need (file:line), and the stage compiles in
  # about half the CPU time (test_model.cpp: 80 s -> 28 s) while its tests run
  # ~15% longer (test_sim's long rollouts, measured). SCANDYN_HOST_EFFECT_SETS=OFF:
  # the host simulator's steps and step derivatives with every joint effect compiled
  # in (the same numbers; CMakeLists.txt), 4 effect sets instead of 64:
  # cpu_fallback/simulator_step.cpp and step_derivatives.cpp took 320 of the stage's
  # 1190 compile-seconds with all of them.
  if build_stage asan "$asan_build" -DCMAKE_BUILD_TYPE=RelWithDebInfo \
       "-DCMAKE_CXX_FLAGS_RELWITHDEBINFO=-O1 -g1 -DNDEBUG" \
       -DSCANDYN_SANITIZE=address,undefined -DSCANDYN_BENCH=OFF -DSCANDYN_CUDA=OFF \
       -DSCANDYN_HOST_EFFECT_SETS=OFF; then
    wait_report
    test_stage asan "$asan_build" -E "$asan_long" || failed+=(asan)
  else
    failed+=(asan)
    failed_tests+=("asan: configure or build failed")
  fi
fi
wait_report

if [[ "${SCANDYN_SKIP_FUZZ:-0}" != 1 ]]; then
  if command -v clang++ >/dev/null 2>&1; then
    stamp "fuzz: ${SCANDYN_FUZZ_SECONDS:-10} s per target (build-fuzz)"
    scripts/fuzz.sh "${SCANDYN_FUZZ_SECONDS:-10}" ||
      { failed+=(fuzz); failed_tests+=("fuzz: the fuzz targets' build or a target failed (above)"); }
  else
    echo "test.sh: warning: clang++ not found; the fuzz stage is skipped" >&2
  fi
fi

elapsed=$((SECONDS - start))
if ((${#failed[@]})); then
  if ((${#failure_tails[@]})); then
    echo "the failed tests' output (last lines each):"
    printf '%s\n' "${failure_tails[@]}"
  fi
  if ((${#failed_tests[@]})); then
    echo "what failed (stage: test or step; the stage's output above has the details):"
    printf '  %s\n' "${failed_tests[@]}"
  fi
  stamp "FAILED: ${failed[*]} ($((elapsed / 60))m$((elapsed % 60))s)"
  exit 1
fi
stamp "all stages passed ($((elapsed / 60))m$((elapsed % 60))s)"
