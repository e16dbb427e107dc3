#!/usr/bin/env bash
# scripts/demo.sh: the main job. Installs what is missing, builds the `scandyn`
# command (Release, without tests and benchmarks) and runs it on the built-in
# defaults: the KUKA iiwa arm (the shipped models/iiwa.urdf, or $SCANDYN_MODELS_DIR)
# and a generated 1000-link rope.
#   1. `scandyn info`  the DoF order
#   2. `scandyn eval`  inverse dynamics, forward dynamics and bias forces of 5
#                      random states, written to build-demo/out.csv
#   3. `scandyn bench` serial and OpenMP timings, one CSV row each
# Environment: SCANDYN_DEMO_BUILD_DIR (default build-demo), SCANDYN_SKIP_SETUP=1.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

build=${SCANDYN_DEMO_BUILD_DIR:-build-demo}
[[ "${SCANDYN_SKIP_SETUP:-0}" == 1 ]] || scripts/setup.sh
# Without a GPU the demo runs the CPU backends only: the CUDA code (compiled when nvcc
# is found) is built in its reduced kernel set, as scripts/test.sh does (README)
cuda=()
if ! nvidia-smi -L >/dev/null 2>&1; then
  cuda=(-DSCANDYN_SIM_EFFECT_SETS=OFF -DSCANDYN_CUDA_ALL_CAPACITIES=OFF -DCMAKE_CUDA_ARCHITECTURES=90-virtual)
fi
cmake -S . -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=Release -DSCANDYN_TESTS=OFF -DSCANDYN_BENCH=OFF \
  ${cuda[@]+"${cuda[@]}"} >/dev/null
cmake --build "$build" --target scandyn_cli
scandyn=$build/scandyn

models=${SCANDYN_MODELS_DIR:-models}
arm=$models/iiwa.urdf
if [[ ! -f "$arm" ]]; then
  echo "demo: $arm not found (set SCANDYN_MODELS_DIR); using the generated chain:7 instead"
  arm=chain:7
fi

echo
echo "== scandyn info --model $arm"
"$scandyn" info --model "$arm"

# five random states: q_i, qd_i, qdd_i, tau_i for the 7 DoFs
states=$build/states.csv
python3 - "$states" <<'EOF'
import random, sys
random.seed(1)
n = 7
cols = [f'{k}_{i}' for k in ('q', 'qd', 'qdd', 'tau') for i in range(n)]
with open(sys.argv[1], 'w') as f:
    f.write(','.join(cols) + '\n')
    for _ in range(5):
        f.write(','.join('%.6f' % random.uniform(-1, 1) for _ in cols) + '\n')
EOF
echo
echo "== scandyn eval --model $arm --states $states --out $build/out.csv --algo id,fd,bias"
"$scandyn" eval --model "$arm" --states "$states" --out "$build/out.csv" --algo id,fd,bias
cut -d, -f1-7 "$build/out.csv" | sed 's/^/  /'
echo "  ($(head -n1 "$build/out.csv" | tr ',' '\n' | wc -l) columns: tau_id_*, qdd_fd_*, h_*)"

echo
echo "== scandyn bench (one row per configuration)"
echo "algo,strategy,backend,precision,model,links,instances,seconds_per_call,evals_per_second,max_rel_err"
for backend in serial openmp; do
  "$scandyn" bench --model "$arm" --algo id --instances 100000 --backend "$backend" --min-time 0.3
  "$scandyn" bench --model "$arm" --algo fd --instances 100000 --backend "$backend" --min-time 0.3
done
"$scandyn" bench --model "$arm" --algo id --instances 100000 --precision float --min-time 0.3
"$scandyn" bench --model rope:1000 --algo id --instances 100 --min-time 0.3
"$scandyn" bench --model rope:1000 --algo fd --instances 100 --min-time 0.3
"$scandyn" bench --model rope:100000 --algo id --instances 1 --strategy scan-world --precision float --min-time 0.3
