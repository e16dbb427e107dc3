#!/usr/bin/env bash
# bench/compare/gpu.sh: scandyn CUDA against MuJoCo Warp, MJX and GRiD on this GPU, side by side.
#
#   bench/compare/gpu.sh [OUTDIR] [--scandyn PATH] [gpu.py flags...]      (OUTDIR default: $OUT)
#
# Offline machine: the peers come as wheels in .whl/ (bench/compare/fetch_wheels.sh fetches
# them on a networked machine), installed with pip --no-index into /tmp/site; urdfdom and the
# models as scripts/prepare_device.sh stages them (.deps/root), as for gpu_check.sh; the robot models ship in models/.
# Steps (each logged; the run stops itself at --deadline seconds, default 540, and every row
# measured until then is in the CSV):
#   1. environment (GPU, driver, nvcc, Python packages)               -> OUTDIR/env.txt
#   2. wheels from .whl/ into /tmp/site (PYTHONPATH), with any wheel whose parts
#      bench/compare/stage_wheels.sh staged in earlier calls (MuJoCo Warp: see fetch_wheels.sh)
#   3. scandyn: --scandyn PATH, or configured as gpu_check.sh does (Release, CUDA, sm_90,
#      -march=native, staged urdfdom) and only the `scandyn_cli` target (the command) built, in
#      $SCANDYN_GPU_BUILD_DIR (default build-gpu; an existing build is reused) -> OUTDIR/build.log
#   4. bench/compare/gpu.py -> OUTDIR/compare-<device>.csv, OUTDIR/gpu.log,
#      OUTDIR/logs.tar.gz (one log per library and model)
# Environment: SCANDYN_COMPARE_DEVICE (default from nvidia-smi, e.g. h100), SCANDYN_JOBS.
set -uo pipefail
export SCANDYN_COMPARE_START=${SCANDYN_COMPARE_START:-$(date +%s)}
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
repo=$PWD

out=${OUT:-}
scandyn=
pass=()
while (($#)); do
  case $1 in
    --scandyn) scandyn=$2; shift 2 ;;
    --*) pass+=("$1"); [[ $# -gt 1 && $2 != --* ]] && { pass+=("$2"); shift; }; shift ;;
    *) out=$1; shift ;;
  esac
done
[[ -n "$out" ]] || { echo "gpu.sh: no output directory: pass it or set \$OUT" >&2; exit 2; }
mkdir -p "$out"
out=$(cd "$out" && pwd)
note() { printf '\n==== [%s +%ss] %s\n' "$(date +%H:%M:%S)" "$(($(date +%s) - SCANDYN_COMPARE_START))" "$*"; }

if ! command -v nvcc >/dev/null 2>&1 && [[ -x /usr/local/cuda/bin/nvcc ]]; then
  export PATH=/usr/local/cuda/bin:$PATH
fi
if [[ -z "${SCANDYN_MODELS_DIR:-}" ]]; then
  for d in "$repo/models"; do
    [[ -d "$d" ]] && { export SCANDYN_MODELS_DIR=$(cd "$d" && pwd); break; }
  done
fi
device=${SCANDYN_COMPARE_DEVICE:-$(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -n1 |
  awk '{for (i = 1; i <= NF; i++) if ($i != "NVIDIA") {print tolower($i); exit}}')}
device=${device:-gpu}

# ---- 2. wheels ------------------------------------------------------------------------------------
note "wheels from .whl/ -> /tmp/site"
source bench/compare/install_wheels.sh
export MUJOCO_GL=${MUJOCO_GL:-egl}

# ---- 1. environment -------------------------------------------------------------------------------
{
  echo "date: $(date -u +%Y-%m-%dT%H:%M:%SZ)"
  echo "host: $(uname -srm), $(nproc) cores, $(awk -F': ' '/^model name/ {print $2; exit}' /proc/cpuinfo)"
  echo "commit: $(git rev-parse --short HEAD 2>/dev/null || echo '?')"
  echo "nvcc: $(nvcc --version 2>/dev/null | tail -n2 | paste -sd' ')"
  echo "python: $(python3 --version 2>&1) ($(command -v python3))"
  nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv 2>&1
  echo "packages:"
  python3 - <<'EOF' 2>&1
from importlib import metadata
for d in ('numpy', 'mujoco', 'mujoco-mjx', 'mujoco-warp', 'warp-lang', 'jax', 'jaxlib', 'torch', 'grid-rbd', 'trimesh'):
    try:
        print('  %s %s' % (d, metadata.version(d)))
    except Exception:
        print('  %s: not installed' % d)
EOF
  ls -la .whl 2>/dev/null
} >"$out/env.txt"
cat "$out/env.txt"

# ---- 3. scandyn -----------------------------------------------------------------------------------
if [[ -z "$scandyn" ]]; then
  build=${SCANDYN_GPU_BUILD_DIR:-build-gpu}
  note "scandyn: configure and build the scandyn_cli target in $build -> $out/build.log"
  deps=$repo/.deps/root
  args=()
  if [[ -d "$deps/usr" ]]; then
    urdfdom_cfg=$(find "$deps/usr/lib" -path '*/urdfdom/cmake/urdfdom-config.cmake' 2>/dev/null | head -n1)
    libdir=$(dirname "$(dirname "$(dirname "$urdfdom_cfg")")")
    export LD_LIBRARY_PATH=$libdir${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
    args+=(-DCMAKE_PREFIX_PATH="$deps/usr")
  fi
  {
    cmake -S . -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=Release -DSCANDYN_CUDA=ON \
      -DCMAKE_CUDA_ARCHITECTURES="${CMAKE_CUDA_ARCHITECTURES:-90}" -DSCANDYN_NATIVE=ON ${args[@]+"${args[@]}"} &&
      cmake --build "$build" --parallel "${SCANDYN_JOBS:-$(nproc)}" --target scandyn_cli
  } >"$out/build.log" 2>&1 || { tail -n 30 "$out/build.log"; echo "gpu.sh: scandyn build failed" >&2; exit 1; }
  scandyn=$repo/$build/scandyn
else
  [[ -d "$repo/.deps/root/usr" ]] && export LD_LIBRARY_PATH=$(dirname "$(find "$repo/.deps/root/usr/lib" -name 'liburdfdom_model.so*' | head -n1)")${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
fi
"$scandyn" info --model rope:2 | grep '^cuda' | tee -a "$out/env.txt"

# ---- 4. compare -----------------------------------------------------------------------------------
note "compare on $device -> $out/compare-$device.csv"
logs=/tmp/compare-logs
rm -rf "$logs" && mkdir -p "$logs"
PYTHONUNBUFFERED=1 python3 bench/compare/gpu.py --scandyn "$scandyn" --device "$device" \
  --out "$out/compare-$device.csv" --logdir "$logs" ${pass[@]+"${pass[@]}"} 2>&1 | tee "$out/gpu.log"
rc=${PIPESTATUS[0]}
tar -czf "$out/logs.tar.gz" --exclude=./models -C "$logs" . 2>/dev/null
note "done (exit $rc); copy $out/compare-$device.csv to bench/results/ and run bench/compare/plot.py"
exit "$rc"
