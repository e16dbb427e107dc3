#!/usr/bin/env bash
# scripts/multi_gpu_check.sh: the several-GPU checks and measurements (docs/scaling.md)
# on a machine with two or more GPUs, offline, in one command.
#
#   scripts/multi_gpu_check.sh BUILD OUTDIR
#
# BUILD: a CUDA build directory of this tree (scandyn, tests/test_sharded and
# tests/test_sim_devices in it), built here or elsewhere for this GPU (a build with
# -DBUILD_SHARED_LIBS=ON travels small: BUILD holds libscandyn.so). Steps:
#   1. the GPUs and their links                                   -> env.txt
#   2. pip install of the Python package (CUDA, no per-effect-set kernels) into
#      /tmp/scandyn-site, in the background, niced, while 3 and 4 run -> pip.log
#   3. the sharded engines' and simulator's tests on every device  -> tests.log, and
#      their CUDA tests under compute-sanitizer memcheck            -> sanitizer.log
#   4. scripts/bench_multi_gpu.sh: one GPU against all, one process -> multi_gpu.csv,
#      multi_gpu_speedup.csv
#   5. examples/multi_gpu_torchrun.py --measure id, fd, step (the RL step) and rollout (the
#      env with its policy) with one process and
#      under torchrun --nproc-per-node <GPUs>, rollout under mpirun   -> python.jsonl
#      (the JSON rows), python.log
#   6. python/tests/test_multi_gpu.py on these GPUs (the installed package)  -> pytest.log
# urdfdom comes from .deps/root (scripts/prepare_device.sh), gymnasium from .whl/.
# NVLink multicast stays off in every process started here.
set -uo pipefail

cd "$(dirname "${BASH_SOURCE[0]}")/.."
repo=$PWD
build=$(cd "${1:?usage: multi_gpu_check.sh BUILD OUTDIR}" && pwd)
out=${2:?usage: multi_gpu_check.sh BUILD OUTDIR}
mkdir -p "$out"
out=$(cd "$out" && pwd)
note() { printf '\n==== [%s] %s\n' "$(date +%H:%M:%S)" "$*"; }
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1
export OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1

cfg=$(find "$repo/.deps/root/usr/lib" -path '*/urdfdom/cmake/urdfdom-config.cmake' 2>/dev/null | head -n1)
[[ -n "$cfg" ]] || { echo "multi_gpu_check.sh: no urdfdom under .deps/root: run scripts/prepare_device.sh" >&2; exit 2; }
libdir=$(dirname "$(dirname "$(dirname "$cfg")")")
export LD_LIBRARY_PATH=$build:$libdir:/usr/local/cuda/lib64${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
export CMAKE_PREFIX_PATH=$repo/.deps/root/usr${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}
export SCANDYN_MODELS_DIR=$repo/models
[[ -x /usr/local/cuda/bin/nvcc ]] && export PATH=/usr/local/cuda/bin:$PATH
gpus=$(nvidia-smi -L 2>/dev/null | grep -c '^GPU' || true)

# ---- 1 -------------------------------------------------------------------------------
{
  date -u +%Y-%m-%dT%H:%M:%SZ
  echo "commit: $(git -C "$repo" rev-parse --verify -q HEAD 2>/dev/null || echo unknown)"
  echo "host: $(uname -srm), $(nproc) cores"
  nvidia-smi -L
  nvidia-smi topo -m
  nvidia-smi --query-gpu=index,name,memory.total,pcie.link.gen.current,pcie.link.width.current --format=csv
  python3 -c 'import torch; print("torch", torch.__version__)' 2>&1
} >"$out/env.txt" 2>&1
cat "$out/env.txt"

# ---- 2 -------------------------------------------------------------------------------
site=/tmp/scandyn-site
note "pip install . (background) -> $out/pip.log"
(
  t0=$(date +%s)
  CMAKE_BUILD_PARALLEL_LEVEL=$(nproc) nice -n 19 python3 -m pip install -v --no-build-isolation --no-index \
    --no-deps --upgrade --target "$site" . -C cmake.define.CMAKE_CUDA_ARCHITECTURES=90 \
    -C cmake.define.SCANDYN_SIM_EFFECT_SETS=OFF -C cmake.define.SCANDYN_TRUTH=OFF
  rc=$?
  python3 -m pip install -q --no-index --no-deps --target "$site" "$repo"/.whl/*.whl
  echo "pip install: $(($(date +%s) - t0)) s, exit $rc"
) >"$out/pip.log" 2>&1 &
pip_pid=$!

# ---- 3 -------------------------------------------------------------------------------
note "tests -> $out/tests.log"
for t in test_sharded test_sim_devices; do
  echo "== $t" >>"$out/tests.log"
  "$build/tests/$t" >>"$out/tests.log" 2>&1
  echo "== $t exit $?" | tee -a "$out/tests.log"
done

# compute-sanitizer memcheck on the CUDA tests of both programs (the sharded engines'
# and simulator's kernels and copies on every device)
if command -v compute-sanitizer >/dev/null; then
  note "compute-sanitizer memcheck -> $out/sanitizer.log"
  for t in test_sharded test_sim_devices; do
    echo "== $t" >>"$out/sanitizer.log"
    compute-sanitizer --tool memcheck --error-exitcode 3 --leak-check full \
      "$build/tests/$t" --gtest_filter='*Cuda*' >>"$out/sanitizer.log" 2>&1
    echo "== $t memcheck exit $?" | tee -a "$out/sanitizer.log"
  done
fi

# ---- 4 -------------------------------------------------------------------------------
note "bench_multi_gpu.sh -> $out/multi_gpu.csv"
scripts/bench_multi_gpu.sh "$build/scandyn" "$out" all

# ---- 5 -------------------------------------------------------------------------------
note "waiting for pip"
wait "$pip_pid"
tail -n 3 "$out/pip.log"
export PYTHONPATH=$site${PYTHONPATH:+:$PYTHONPATH}
rows=$out/python.jsonl
n=${SCANDYN_MGPU_INSTANCES:-20000000}
envs=${SCANDYN_MGPU_ENVS:-20000000}
ex=examples/multi_gpu_torchrun.py
{
  for what in id fd step; do
    python3 $ex --measure $what --envs "$n" --steps 50 --warmup 3 --out "$rows"
    torchrun --standalone --nproc-per-node "$gpus" $ex --measure $what --envs "$n" --steps 50 --warmup 3 --out "$rows"
  done
  python3 $ex --measure --envs "$envs" --steps 50 --out "$rows"
  torchrun --standalone --nproc-per-node "$gpus" $ex --measure --envs "$envs" --steps 50 --out "$rows"
  mpirun -n "$gpus" -x NCCL_NVLS_ENABLE -x TORCH_SYMM_MEM_DISABLE_MULTICAST -x NVSHMEM_DISABLE_NVLS -x PYTHONPATH \
    -x LD_LIBRARY_PATH python3 examples/multi_gpu_mpi.py --measure --envs "$envs" --steps 50 --out "$rows"
  torchrun --standalone --nproc-per-node "$gpus" $ex --iters 10
} >"$out/python.log" 2>&1
note "python rows"
cat "$rows"

# ---- 6 -------------------------------------------------------------------------------
note "pytest python/tests/test_multi_gpu.py -> $out/pytest.log"
SCANDYN_CLI=$build/scandyn python3 -m pytest -q -rs -p no:cacheprovider python/tests/test_multi_gpu.py \
  >"$out/pytest.log" 2>&1
echo "pytest exit $?"
tail -n 5 "$out/pytest.log"
