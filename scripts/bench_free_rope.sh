#!/usr/bin/env bash
# scripts/bench_free_rope.sh: a free rope (--floating-base: a floating base, then
# N - 1 links) against the fixed rope:N on the same engine, through `scandyn bench`:
# forward dynamics by the parallel chain engine (--fd parallel) and inverse dynamics
# by the link scans (scan-local, scan-world; not on cuda, whose bench rows for the
# scans are in bench_cuda_id), in float and double, REPEAT rounds alternating fixed
# and free. Appends the rows to OUT.csv (bench/results format) and prints, per
# algorithm, strategy and precision, the ratio of the free rope's median time to
# the fixed rope's (the issue's target for fd on the GPU: <= 1.2).
#
#   scripts/bench_free_rope.sh SCANDYN BACKEND N OUT.csv [THREADS] [REPEAT]
#
# e.g. scripts/bench_free_rope.sh build-cpu/scandyn openmp 100000 out.csv 2
#      scripts/bench_free_rope.sh build-gpu/scandyn cuda 1000000 out.csv
set -euo pipefail
[[ $# -ge 4 ]] || { sed -n '2,16p' "$0" >&2; exit 2; }
scandyn=$1 backend=$2 n=$3 out=$4 threads=${5:-} repeat=${6:-3}
threads_flag=()
[[ -n "$threads" ]] && threads_flag=(--threads "$threads")
rows=$(mktemp)
trap 'rm -f "$rows"' EXIT
run() {  # run ALGO-FLAGS...
  for prec in float double; do
    for r in $(seq "$repeat"); do
      for base in fixed floating; do
        local fb=()
        [[ $base == floating ]] && fb=(--floating-base)
        OMP_WAIT_POLICY=passive "$scandyn" bench --model "rope:$n" "${fb[@]}" "$@" --backend "$backend" \
          "${threads_flag[@]}" --instances 1 --precision "$prec" --min-time 1 --csv "$out" | tee -a "$rows"
      done
    done
  done
}
run --algo fd --fd parallel
if [[ $backend != cuda ]]; then
  run --algo id --strategy scan-local
  run --algo id --strategy scan-world
fi
# median per (algo, strategy, precision, model), then free / fixed
python3 - "$rows" <<'PY'
import csv, statistics, sys
times = {}
for r in csv.reader(open(sys.argv[1])):
    if not r or r[0] == "algo":
        continue
    times.setdefault((r[0], r[1], r[3], r[4].endswith("-floating")), []).append(float(r[7]))
for (algo, strat, prec, floating), t in sorted(times.items()):
    if floating:
        continue
    fixed, free = statistics.median(t), statistics.median(times[(algo, strat, prec, True)])
    print(f"{algo} {strat} {prec}: fixed {fixed * 1e3:.3f} ms, free {free * 1e3:.3f} ms, free/fixed {free / fixed:.3f}")
PY
