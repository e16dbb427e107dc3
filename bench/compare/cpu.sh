#!/usr/bin/env bash
# bench/compare/cpu.sh: scandyn (serial, OpenMP) against Pinocchio on this CPU, side by side.
#
#   bench/compare/cpu.sh [--device NAME] [--quick] [--check-only] [extra cpu.py flags...]
#
# 1. .venv with numpy and Pinocchio (`pin`, pinned in scripts/setup_python.sh)
# 2. scandyn's command, CPU only (build dir $SCANDYN_COMPARE_BUILD, default build-compare;
#    or give a built one in $SCANDYN)
# 3. pin_bench and pin_bench_hdr (bench/compare/pin_bench) against the wheel's C++ library
#    and headers (site-packages/cmeel.prefix), in $SCANDYN_COMPARE_BUILD/pin_bench
# 4. bench/compare/cpu.py: the equality check on random states, then the timings;
#    rows to bench/results/compare-<device>.csv (columns: bench/compare/common.py)
#
# --device NAME   the results file's name; default cpu-<vendor>-<N>c from /proc/cpuinfo and nproc
# --quick         iiwa and rope:100 only, batches 1 and 100, 0.05 s per timing (a smoke run)
# --check-only    only the equality check (exit 1 on a mismatch above 1e-9); writes no rows
# Environment: SCANDYN_JOBS (build parallelism, default 2), SCANDYN_MODELS_DIR.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
repo=$PWD

device=
extra=()
quick=0
while (($#)); do
  case $1 in
    --device) device=$2; shift 2 ;;
    --quick) quick=1; shift ;;
    *) extra+=("$1"); shift ;;
  esac
done
if [[ -z "$device" ]]; then
  vendor=$(awk -F': ' '/^model name/ {print tolower($2); exit}' /proc/cpuinfo | awk '{print $1"-"$2}' | tr -cd 'a-z0-9-')
  device="cpu-${vendor:-unknown}-$(nproc)c"
fi
jobs=${SCANDYN_JOBS:-2}
build=${SCANDYN_COMPARE_BUILD:-build-compare}

if [[ -z "${SCANDYN_MODELS_DIR:-}" ]]; then
  for d in "$repo/models"; do
    [[ -d "$d" ]] && { export SCANDYN_MODELS_DIR=$(cd "$d" && pwd); break; }
  done
fi

echo "== python environment"
scripts/setup_python.sh
py=$repo/.venv/bin/python
prefix=$("$py" -c 'import cmeel, os; print(cmeel.__path__[0] + ".prefix")' 2>/dev/null ||
         "$py" -c 'import sysconfig, os; print(os.path.join(sysconfig.get_paths()["purelib"], "cmeel.prefix"))')
[[ -d "$prefix/include/pinocchio" ]] || { echo "cpu.sh: no Pinocchio headers under $prefix" >&2; exit 1; }

if [[ -z "${SCANDYN:-}" ]]; then
  echo "== scandyn (CPU build in $build)"
  cmake -S . -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=Release -DSCANDYN_CUDA=OFF -DSCANDYN_TESTS=OFF \
    -DSCANDYN_BENCH=OFF >/dev/null
  cmake --build "$build" --parallel "$jobs" --target scandyn_cli
  SCANDYN=$repo/$build/scandyn
fi

echo "== pin_bench (Pinocchio from $prefix)"
cmake -S bench/compare/pin_bench -B "$build/pin_bench" -G Ninja -DCMAKE_BUILD_TYPE=Release \
  -DCMAKE_PREFIX_PATH="$prefix" >/dev/null
cmake --build "$build/pin_bench" --parallel "$jobs"
export LD_LIBRARY_PATH=$prefix/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}

args=(--scandyn "$SCANDYN" --pin-bench "$build/pin_bench/pin_bench" --pin-bench-hdr "$build/pin_bench/pin_bench_hdr"
      --device "$device" --out "bench/results/compare-$device.csv")
if ((quick)); then
  args+=(--models iiwa,rope:100 --batches 1,100 --min-time 0.05)
fi
echo "== compare ($device)"
{
  echo "date: $(date -u +%Y-%m-%dT%H:%M:%SZ)"
  echo "cpu: $(awk -F': ' '/^model name/ {print $2; exit}' /proc/cpuinfo), $(nproc) threads"
  echo "compiler: $(c++ --version | head -n1)"
  echo "scandyn: $("$SCANDYN" --version) ($(git rev-parse --short HEAD 2>/dev/null || echo '?'))"
  echo "pinocchio: $("$build/pin_bench/pin_bench" version)"
} | tee "bench/results/compare-$device.env.txt"
"$py" bench/compare/cpu.py "${args[@]}" ${extra[@]+"${extra[@]}"}
# plot.py needs matplotlib (not in scripts/setup_python.sh: the tests do not)
"$py" -c 'import matplotlib' 2>/dev/null || "$py" -m pip install -q --disable-pip-version-check matplotlib ||
  echo "cpu.sh: warning: matplotlib could not be installed; plot.py needs it" >&2
echo "== done: bench/results/compare-$device.csv; plots and the docs table:"
echo "   $py bench/compare/plot.py bench/results/compare-$device.csv --doc docs/benchmarks.md"
