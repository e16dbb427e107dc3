#!/bin/sh
# Runs bench_loop_step's iterative rows (docs/loops.md, "The simulator's iterative loop
# path") and the sparse rows from the same start, and writes
# bench/results/loop_step_iterative.csv and bench/results/loop_step-startx.csv (their
# "#" header lines describe the machine: edit MACHINE for another). Long: cloth:300:300
# takes ~1 min and cloth:1000:1000 ~5 min a step on a 2-core VM.
#   scripts/bench_loop_step_iterative.sh [BUILD_DIR]
set -e
B=${1:-build-dev}
T=$(mktemp -d)
MACHINE=${MACHINE:-"the shared 2-core development VM (AMD EPYC, 2 vCPUs, 23 GB; other engineers' work beside)"}
COMMIT=$(git rev-parse --short HEAD)
it="$B/bench_loop_step --iterative --start x --torque 1e-4"
$it --steps 5 --cloth 10:10 --cloth 30:30 --cloth 50:50 > "$T/a.csv"
$it --steps 3 --cloth 100:100 > "$T/b.csv"
$it --steps 2 --quick --cloth 300:300 > "$T/c.csv"
$it --steps 1 --quick --max-iterations 1 --cloth 1000:1000 > "$T/d.csv"
$it --steps 1 --quick --max-iterations 1500 --max-seconds 0 --cloth 1000:1000 > "$T/e.csv" 2> "$T/e.log"
$B/bench_loop_step --start x --steps 3 --cloth 30:30 --cloth 50:50 > "$T/s.csv"
$B/bench_loop_step --start x --steps 2 --cloth 100:100 >> "$T/s.csv"
{
  echo "# The simulator's step of cloth grids with their loop closures on the iterative loop path (scene \"loop_solver\": \"iterative\"; docs/loops.md). Machine: $MACHINE, $(date -u +%F), commit $COMMIT, serial simulator backend, double."
  echo "# rk4, dt 1e-4 s, gravity; --start x: q = 0.1 and qd = 0.5 on every x-axis joint, 0 on the others (closed); --torque 1e-4: tau_i = 1e-4 sin(1 + i) N m at every step. Columns: bench/bench_loop_step.cpp (--iterative)."
  echo "# Commands: $it --steps 5 --cloth 10:10 --cloth 30:30 --cloth 50:50; ... --steps 3 --cloth 100:100; ... --steps 2 --quick --cloth 300:300; ... --steps 1 --quick --max-iterations 1 --cloth 1000:1000"
  echo "# cloth:1000:1000 cold solve alone (... --quick --max-iterations 1500 --max-seconds 0): $(grep 'cold forward dynamics' "$T/e.log" | tail -1)"
  head -1 "$T/a.csv"
  for f in a b c d; do tail -n +2 "$T/$f.csv"; done
} > bench/results/loop_step_iterative.csv
{
  echo "# The sparse loop path (CHOLMOD) from the iterative rows' start: $MACHINE, $(date -u +%F), commit $COMMIT, serial backend, rk4, dt 1e-4 s, gravity, --start x, tau = 0 (a direct factorisation's cost does not depend on the right-hand side)."
  echo "# Commands: $B/bench_loop_step --start x --steps 3 --cloth 30:30 --cloth 50:50; ... --steps 2 --cloth 100:100 (columns: bench/results/loop_step.csv)."
  head -1 "$T/s.csv"
  grep -v '^grid' "$T/s.csv"
} > bench/results/loop_step-startx.csv
rm -r "$T"
