#!/usr/bin/env bash
# bench/compare/simd_callgrind.sh: instructions per instance (valgrind callgrind, Ir)
# of scandyn's CPU recursions with and without the SIMD path (--simd on / off), and
# of Pinocchio's per-call rnea / aba / crba, on one model in double: a measure that
# other processes on a loaded machine do not disturb (wall-clock rates: cpu.sh).
#
#   bench/compare/simd_callgrind.sh SCANDYN PIN_BENCH [MODEL] [INSTANCES] > rows.csv
#
# SCANDYN: a built scandyn command; PIN_BENCH: bench/compare/pin_bench's pin_bench
# (cpu.sh builds both). MODEL: a URDF under models/ (default iiwa), INSTANCES per
# batch (default 1024). Only the compute functions are counted (--toggle-collect: the
# engine's compute(); Pinocchio 4's impl::rnea, impl::abaLocalConvention and
# impl::crbaLocalConvention, what its rnea, aba and crba call), over the warm-up call
# and one timed call (--min-time 0), so Ir / (2 x INSTANCES) is per instance. Valgrind
# runs no AVX-512: give it a build without SCANDYN_NATIVE on such a machine.
# Columns: algo,library,variant,model,instances,ir_per_instance
set -euo pipefail
scandyn=$1
pin=$2
model=${3:-iiwa}
B=${4:-1024}
urdf=$(cd "$(dirname "${BASH_SOURCE[0]}")/../../models" && pwd)/$model.urdf
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

# Ir collected inside functions matching $1, running the rest of the arguments.
ir() {
  local pattern=$1
  shift
  valgrind --tool=callgrind --toggle-collect="$pattern" --callgrind-out-file="$tmp/cg.out" "$@" >/dev/null 2>"$tmp/cg.err" ||
    { cat "$tmp/cg.err" >&2; exit 1; }
  awk '/^(summary|totals):/ {print $2; exit}' "$tmp/cg.out"
}

echo "algo,library,variant,model,instances,ir_per_instance"
for algo in id fd mass; do
  case $algo in
    id) engine='*CpuInverseDynamics<double>::compute*'; pfn='*pinocchio::impl::rnea<*' ;;
    fd) engine='*CpuForwardDynamics<double>::compute*'; pfn='*pinocchio::impl::abaLocalConvention<*' ;;
    mass) engine='*CpuMassMatrix<double>::compute*'; pfn='*pinocchio::impl::crbaLocalConvention<*' ;;
  esac
  for simd in off on; do
    n=$(ir "$engine" "$scandyn" bench --model "$urdf" --algo "$algo" --instances "$B" --backend openmp --threads 1 \
          --simd "$simd" --min-time 0)
    echo "$algo,scandyn,simd-$simd,$model,$B,$(awk -v n="$n" -v b="$B" 'BEGIN {printf "%.1f", n / (2 * b)}')"
  done
  n=$(ir "$pfn" "$pin" bench --urdf "$urdf" --algo "$algo" --name "$model" --instances "$B" --min-time 0)
  echo "$algo,pinocchio,per-call,$model,$B,$(awk -v n="$n" -v b="$B" 'BEGIN {printf "%.1f", n / (2 * b)}')"
done
