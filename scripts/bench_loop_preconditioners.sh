#!/bin/sh
# Runs bench_loop_step's iterative rows once per preconditioner of the iterative loop
# solver (sim::LoopPreconditioner; docs/loops.md, "The simulator's iterative loop path",
# "Preconditioner"), interleaved grid by grid, and writes
# bench/results/loop_preconditioners.csv (its "#" header lines: machine, load, commit,
# commands; edit MACHINE for another). About 10 minutes on a 2-core VM.
#   scripts/bench_loop_preconditioners.sh [BUILD_DIR]
set -e
B=${1:-build-dev}
T=$(mktemp -d)
MACHINE=${MACHINE:-"the shared 2-core development VM (AMD EPYC, 2 vCPUs, 23 GB; other engineers' work beside)"}
COMMIT=$(git rev-parse --short HEAD)
P=${PRECONDITIONERS:-block-jacobi,ssor,symmetric-gauss-seidel,block-tridiagonal,block-dilu}
it="$B/bench_loop_step --iterative --start x --torque 1e-4 --preconditioner $P"
load() { cut -d' ' -f1-3 /proc/loadavg; }
L0=$(load)
$it --steps 5 --cloth 30:30 --cloth 50:50 > "$T/a.csv" 2> "$T/a.log"
L1=$(load)
$it --steps 3 --cloth 100:100 > "$T/b.csv" 2> "$T/b.log"
L2=$(load)
$B/bench_loop_step --iterative --start x --torque 1e-4 --preconditioner block-jacobi,ssor --steps 2 --quick --cloth 300:300 > "$T/c.csv" 2> "$T/c.log"
L3=$(load)
{
  echo "# The iterative loop solver's preconditioners (sim::LoopPreconditioner; docs/loops.md, \"Preconditioner\") on the simulator's step of cloth grids. Machine: $MACHINE, $(date -u +%F), commit $COMMIT, serial simulator backend, double."
  echo "# Load (1, 5, 15 min averages of /proc/loadavg) before and after each command: $L0; $L1; $L2; $L3."
  echo "# rk4, dt 1e-4 s, gravity; --start x: q = 0.1 and qd = 0.5 on every x-axis joint, 0 on the others (closed); --torque 1e-4: tau_i = 1e-4 sin(1 + i) N m at every step. Columns: bench/bench_loop_step.cpp (--iterative); solver iterative-cgls-<preconditioner>-torque; the *_none columns (no preconditioner) are run once per grid and repeated; -1: not converged within 20000 iterations (or not run: --quick)."
  echo "# Commands: $it --steps 5 --cloth 30:30 --cloth 50:50; ... --steps 3 --cloth 100:100; and for cloth:300:300 with block-jacobi and ssor only: $B/bench_loop_step --iterative --start x --torque 1e-4 --preconditioner block-jacobi,ssor --steps 2 --quick --cloth 300:300"
  head -1 "$T/a.csv"
  for f in a b c; do tail -n +2 "$T/$f.csv"; done
} > bench/results/loop_preconditioners.csv
cat "$T/a.log" "$T/b.log" "$T/c.log" > bench/results/loop_preconditioners.log
rm -r "$T"
