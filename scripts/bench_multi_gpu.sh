#!/usr/bin/env bash
# scripts/bench_multi_gpu.sh: one GPU against several in one process (docs/scaling.md).
#
#   scripts/bench_multi_gpu.sh SCANDYN OUTDIR [DEVICES]
#
# SCANDYN: the scandyn program of a CUDA build; OUTDIR gets multi_gpu.csv (bench rows,
# scandyn bench's columns plus `devices`, the --devices value with + for commas) and multi_gpu_speedup.csv (each row's
# evals_per_second over the one-device row of the same workload). DEVICES: the
# several-device list (default all). Rows, float, instances from SCANDYN_MGPU_INSTANCES
# (default 2x10^7):
#   iiwa id and fd (aba), device-resident and host-memory rows;
#   the RL step of scenes/iiwa_rl.json (ABA + semi-implicit Euler, gravity, damping);
#   rope:10^6 fd (the parallel chain FD) on 16 instances.
# Each workload runs on device 0 alone, then on DEVICES, in the same process
# environment. NVLink multicast stays off (NCCL_NVLS_ENABLE=0 and the others; the
# engines themselves use no NCCL).
set -euo pipefail

scandyn=${1:?usage: bench_multi_gpu.sh SCANDYN OUTDIR [DEVICES]}
out=${2:?usage: bench_multi_gpu.sh SCANDYN OUTDIR [DEVICES]}
devices=${3:-all}
instances=${SCANDYN_MGPU_INSTANCES:-20000000}
min_time=${SCANDYN_MGPU_MIN_TIME:-1}
repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1
mkdir -p "$out"
csv=$out/multi_gpu.csv
: >"$csv.tmp"

# bench LABEL DEVICES ARGS...: the rows of one scandyn bench, each with the devices column
bench() {
  local devs=$1
  shift
  echo "+ scandyn bench $* --devices $devs" >&2
  "$scandyn" bench "$@" --backend cuda --precision float --min-time "$min_time" --devices "$devs" |
    sed "s/\$/,${devs//,/+}/" >>"$csv.tmp"
}

for devs in 0 "$devices"; do
  bench "$devs" --model iiwa --algo id --instances "$instances"
  bench "$devs" --model iiwa --algo fd --instances "$instances"
  bench "$devs" --algo step --scene "$repo/scenes/iiwa_rl.json" --instances "$instances"
  bench "$devs" --model rope:1000000 --algo fd --instances 16
done
{
  echo "algo,strategy,backend,precision,model,links,instances,seconds_per_call,evals_per_second,max_rel_err,devices"
  cat "$csv.tmp"
} >"$csv"
rm -f "$csv.tmp"

# speedup of each several-device row over the one-device row of the same workload
# (algo, model, instances, and host or resident: the strategy's "-host")
awk -F, 'NR == 1 { next }
  { kind = ($2 ~ /-host$/) ? "host" : "resident"; key = $1 "," $5 "," $7 "," kind
    if ($11 == "0") one[key] = $9; else { many[key] = $9; devs[key] = $11; strat[key] = $2 } }
  END { print "algo,model,instances,row,devices,strategy,evals_per_second_one,evals_per_second_many,speedup"
        for (k in many) if (k in one) printf "%s,%s,%s,%.6g,%.6g,%.3f\n", k, devs[k], strat[k], one[k], many[k], many[k] / one[k] }' \
  "$csv" | { IFS= read -r header; echo "$header"; sort; } >"$out/multi_gpu_speedup.csv"
cat "$csv"
echo
column -s, -t "$out/multi_gpu_speedup.csv" 2>/dev/null || cat "$out/multi_gpu_speedup.csv"
