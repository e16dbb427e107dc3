#!/usr/bin/env bash
# bench/compare/floating_cpu.sh: hyq on a floating base, scandyn serial ABA / RNEA against
# Pinocchio's free-flyer ABA / RNEA (pin_bench --root free), one instance per call, double,
# three alternating rounds in one run (docs/benchmarks.md, "Floating base").
#
#   bench/compare/floating_cpu.sh BUILD_DIR VENV_PYTHON OUT.csv
#
# BUILD_DIR holds the scandyn program (a CPU or CUDA build); VENV_PYTHON the python of a
# .venv with Pinocchio's wheel (scripts/setup_python.sh), whose C++ library and headers
# pin_bench is built against (in /tmp/pinb).
set -euo pipefail
b=$(cd "$1" && pwd); py=$2; out=$(cd "$(dirname "$3")" && pwd)/$(basename "$3")
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
prefix=$("$py" -c 'import cmeel, os; print(cmeel.__path__[0] + ".prefix")')
cmake -S bench/compare/pin_bench -B /tmp/pinb -G Ninja -DCMAKE_BUILD_TYPE=Release -DCMAKE_PREFIX_PATH="$prefix" >/dev/null
cmake --build /tmp/pinb --parallel 2 --target pin_bench >/dev/null
export LD_LIBRARY_PATH=$prefix/lib
export SCANDYN_MODELS_DIR=$PWD/models
echo "algo,strategy,backend,precision,model,links,instances,seconds_per_call,evals_per_second,library,round" > "$out"
for r in 1 2 3; do
  for algo in fd id; do
    "$b/scandyn" bench --model hyq --floating-base --algo $algo --backend serial --precision double --instances 1 --min-time 1 \
      | grep -v '^algo' | cut -d, -f1-9 | sed "s/\$/,scandyn,$r/" >> "$out"
    /tmp/pinb/pin_bench bench --urdf models/hyq.urdf --name hyq-floating --algo $algo --instances 1 --min-time 1 --root free \
      | grep -v '^algo' | cut -d, -f1-9 | sed "s/\$/,pinocchio $(/tmp/pinb/pin_bench version | tr ',' ' '),$r/" >> "$out"
  done
done
cat "$out"
